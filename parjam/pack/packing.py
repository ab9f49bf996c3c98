"""Jammed packings: the O'Hern bisection to phi_c, the dphi ladder (compression up from phi_c,
or decompression down to it) and target pressures, from a random (infinite-temperature) start
(parjam.pack.randomstart; its names stay importable from here).

O'Hern, Silbert, Liu & Nagel, PRE 68, 011306 (2003): a configuration is compressed or
decompressed and re-minimised until its energy per particle lies in a tiny window above zero;
the volume fraction there is its phi_c.  The step in phi is chosen by bisection of the bracket
[unjammed, overjammed], accelerated (and always kept inside the bracket) by the prediction of
the virial relation for a jammed state, E ~ (phi - phi_c)^alpha, dE/dphi = p V / phi, which gives
phi_c ~= phi - alpha E phi / (p V) while the contact network does not change.

The energy window alone leaves phi_c off by the dphi of that state (~2.5e-8 for harmonic spheres
at E/N ~ 1.5e-16; ~4e-7 for alpha = 2.5), which mislabels every state below a few 1e-8.  So the
bisection's phi_c is refined from the jammed side (``refine_phi_c``): the virial relation of the
fixed contact network is applied again to states decompressed towards phi_c, until two successive
estimates (from states at decreasing dphi) agree; their difference is the resolution of phi_c,
recorded with every state.  Every returned state is also checked to be a stable minimum
(parjam.pack.stability) and, where it is a saddle, pushed out of it along its softest direction and
minimised again, or else taken through a compression cycle (``stabilise``).  A ladder step that
unjams is made again in smaller sub-steps, Newton first (``rejam``); if it still unjams,
``LadderUnjammed`` ends the ladder, carrying the jammed states made before it.

On the decomposition: the Jammer holds the state in its force field's PETSc block
rows (positions, diameters, species of this rank's rows; box and constants), never all N of
them, and starts from them (parjam.pack.randomstart.start_rows makes a random start's rows; a whole
Packing is cut into them).  Every per-state number comes from parjam.pack.jamnet on the slabs
(``network``), the stability check and the escapes from parjam.pack.stability on the same
half-edges, Newton from the force field's distributed neighbour list; a State keeps its block
rows (``state_rows``, parjam.pack.staterows), from which parjam.study.members writes its file by row
blocks.  On one rank every number is the serial one bitwise.

(Over 500 lines: the Jammer is one state machine over one force field and its checkpoint; every
minimisation, the escapes' and the cycles' included, goes through its checkpointed ``relax``, so
they are its methods; the stability test itself and the escape searches live in
parjam.pack.stability.)
"""

from dataclasses import dataclass, field

import numpy as np

from parjam import env
from parjam.net import exactsum
from parjam.pack import jamnet, minimize, stability
from parjam.vib import hessian
from parjam.errors import ParjamError, UnjammedError
from parjam.pack.forces import ForceField
from parjam.logstage import log_stage
from parjam.pack.staterows import StateRows
from parjam.pack.protocol import (DEFAULT_ALPHA, DEFAULT_DISPERSITY, DEFAULT_ENERGY_WINDOW,
                             DEFAULT_FTOL, DEFAULT_PHI_START, DEFAULT_RATIO)
# the random start lives in parjam.pack.randomstart; these names stay importable from here
from parjam.pack.randomstart import member_rng, random_packing, start_rows
from parjam.net.system import sphere_volume, wrap

PHI_MAX = {2: 0.99, 3: 0.9}  # the phi_c search gives up above these (nothing jams so late)
# phi_c refinement: each step decompresses to 1/REFINE_RATIO of the estimated distance to phi_c
REFINE_RATIO = 30.0
# relative round-off floor of phi_c's resolution: a few ulps of phi (the box edge, the overlaps
# 1 - r/sigma and E, p of a state all carry relative round-off ~1e-16)
PHI_C_ROUNDOFF = 8.0 * np.finfo(np.float64).eps
RESOLVED_FRACTION = 0.05  # a dphi is resolved when phi_c is known to 5 % of it
MAX_ESCAPES = 6  # saddle escapes (softest direction, then minimisation) per state
# where those fail: compression cycles to these multiples of the state's dphi and back
CYCLE_FACTORS = (10.0, 100.0)
# a ladder step that unjams is made again from the last jammed state in this many sub-steps
REJAM_STEPS = 12
# a returned state is force-balanced to REL_BALANCE of its mean contact force (tighter than
# --ftol near jamming: at dphi = 1e-10 contact forces are ~3e-11), but not below the round-off
# floor FORCE_FLOOR * (mean contact stiffness) of the forces
REL_BALANCE = 1e-5
FORCE_FLOOR = 2e-15


def per_particle(value, n):
    """Whether a metadata value is a per-particle array (n rows)."""
    return isinstance(value, np.ndarray) and value.ndim >= 1 and len(value) == n


def block_rows(comm, pack):
    """This rank's block rows (staterows.StateRows, PETSc's contiguous split of the ids) of a
    whole Packing every rank holds."""
    lo, hi = hessian.row_range(pack.n, comm)
    rows = {k for k, v in pack.meta.items() if per_particle(v, pack.n)}
    meta = {k: (np.array(v[lo:hi]) if k in rows else v) for k, v in pack.meta.items()}
    return StateRows(comm, pack.n, pack.L, pack.alpha, pack.eps, pack.phi, lo,
                     np.array(pack.pos[lo:hi]), np.array(pack.diam[lo:hi]), meta,
                     frozenset(rows))


class LadderUnjammed(UnjammedError):
    """A step of the dphi ladder (or of the target pressures) unjammed: ``states`` are the
    jammed states made before it, ``step`` the dphi (or pressure) that unjammed.  The steps
    after it are not attempted (their phi_c would be another configuration's)."""

    def __init__(self, message, states, step):
        super().__init__(message, collective=False)
        self.states = list(states)
        self.step = step


@dataclass
class JamSettings:
    ftol: float = DEFAULT_FTOL  # max |F| on every particle (eps/sigma units)
    e_low: float = DEFAULT_ENERGY_WINDOW[0]  # energy-per-particle window of the phi_c state
    e_high: float = DEFAULT_ENERGY_WINDOW[1]
    first_step: float = 2e-3  # compression step while unjammed (doubles each time)
    max_iter: int = 200
    ptol: float = 1e-6  # relative tolerance of a target pressure
    fire_rel: float = 1e-4  # FIRE hands over to Newton at max|F| < fire_rel * mean contact force


@dataclass
class State:
    """One minimised state of a configuration: this rank's rows of it (parjam.pack.staterows)."""

    rows: StateRows
    result: minimize.MinResult
    label: str
    info: dict = field(default_factory=dict)

    @property
    def pack(self):
        """The whole configuration on every rank (collective: a gather; the protocol and
        ``parjam pack``'s files never ask for it)."""
        return self.rows.packing()

    @property
    def phi(self):
        return self.rows.phi


class Jammer:
    """Minimises one configuration at chosen volume fractions on communicator ``comm``."""

    def __init__(self, comm, pack, settings=None, progress=None, checkpoint=None):
        """``pack``: a whole system.Packing (the same on every rank), or this rank's block rows
        of one (staterows.StateRows; the random start of parjam.pack.randomstart.start_rows): then
        no rank ever holds all N particles."""
        self.comm = comm
        self.settings = settings or JamSettings()
        self.progress = progress
        self.checkpoint = checkpoint  # parjam.files.checkpoint.Checkpoint, or None
        self.calls = 0  # minimisations so far: the key of their checkpoint records
        # the state: positions only in the force field's block rows (no rank keeps all N of
        # them, the States and their files included: ``state_rows``); box, diameters and constants
        rows = pack if isinstance(pack, StateRows) else block_rows(comm, pack)
        self.n, self.d, self.L = rows.n, rows.d, rows.L
        self.alpha, self.eps = rows.alpha, rows.eps
        # the sum of all N sphere volumes as numpy sums the whole array (bitwise on any P)
        self.sphere_volume = exactsum.total(comm, sphere_volume(rows.diam, self.d), rows.lo,
                                            self.n)
        self.ff = ForceField(comm, rows.diam, rows.L, rows.d, rows.alpha, rows.eps, n=rows.n)
        if rows.lo != self.ff.lo or len(rows.x) != self.ff.hi - self.ff.lo:
            raise ValueError(f"rows [{rows.lo}, {rows.lo + len(rows.x)}) are not the force "
                             f"field's block [{self.ff.lo}, {self.ff.hi})")
        self.ff.local(self.ff.x)[:] = rows.x
        # per-particle metadata (species) kept as the block rows, like the diameters
        self.meta = {k: (np.array(v) if k in rows.row_meta else v) for k, v in rows.meta.items()}
        self.row_meta = set(rows.row_meta)
        self.total_fire = 0
        self.total_newton = 0
        # minimiser steps: a line every 10 s at most (only long minimisations show them)
        throttled = getattr(progress, "throttled", None)
        self._inner = throttled(10.0) if throttled is not None else None

    def _log(self, msg):
        if self.progress is not None:
            self.progress(msg)

    def relax(self, phi=None, e_stop=-np.inf, ftol=None, newton_first=False):
        """Rescale affinely to phi (if given) and minimise; returns the MinResult.  With a
        checkpoint, a minimisation finished in an earlier run is replayed from its record and an
        interrupted one continues from its last snapshot.  ``newton_first``: damped Newton from
        the rescaled state before any FIRE (no inertia: it goes to the minimum of the basin the
        rescaling left the packing in, where FIRE's momentum can carry it out of it)."""
        call, ck = self.calls, self.checkpoint
        self.calls += 1
        record = ck.finished(call) if ck is not None else None
        if record is not None and phi is not None and record["L"] != self.box_for_phi(phi):
            self._log(f"checkpoint record {call + 1} is at another volume fraction than this "
                      f"protocol asks for: recomputing from there")
            ck.discard_from(call)
            record = None
        if record is not None:
            return self._replay(call, record)
        if phi is not None:
            self.rescale(phi)
        calls_before = self.ff.n_force_calls
        resume = self._resume(call) if ck is not None else None
        hook = ck.snapshot(call, self.ff, self.L, calls_before) if ck is not None else None
        try:
            ftol = self.settings.ftol if ftol is None else ftol
            res = None
            if newton_first and resume is None:
                res = minimize.newton(self.ff, ftol, progress=self._inner)
                if res.energy < e_stop:
                    res.status = "unjammed"
                elif not res.ok:
                    steps = res.newton_steps
                    res = None  # FIRE from where Newton stopped (a saddle region)
            if res is None:
                res = minimize.minimize(self.ff, ftol, e_stop,
                                        fire_rel=self.settings.fire_rel, progress=self._inner,
                                        snapshot=hook, resume=resume)
                if newton_first and resume is None:
                    res.newton_steps += steps
        except ValueError as exc:  # e.g. a box too small for the neighbour search
            raise ParjamError(f"at phi = {self.phi:.10f}: {exc}", collective=False) from None
        self.total_fire += res.fire_steps
        self.total_newton += res.newton_steps
        if ck is not None:
            ck.finish(call, self.ff, self.L, res, self.ff.n_force_calls - calls_before)
        return res

    @property
    def phi(self):
        return float(self.sphere_volume / self.volume)

    @property
    def volume(self):
        return self.L**self.d

    def box_for_phi(self, phi):
        """Box edge giving volume fraction phi (system.Packing.box_for_phi)."""
        return float((self.sphere_volume / phi) ** (1.0 / self.d))

    def rescale(self, phi):
        """Affine rescaling of the box and of the owned positions to volume fraction phi
        (system.Packing.rescaled, on the force field's block rows)."""
        L = self.box_for_phi(phi)
        x = self.ff.local(self.ff.x)
        x[:] = wrap(x * (L / self.L), L)
        self.L = L
        self.ff.set_box(L)

    def state_rows(self):
        """A copy of the current state's block rows (staterows.StateRows: positions, diameters,
        per-particle metadata of this rank's ids; O(N/P)), what a State keeps for its file."""
        ff = self.ff
        meta = {k: (np.array(v) if k in self.row_meta else v) for k, v in self.meta.items()}
        return StateRows(self.comm, self.n, self.L, self.alpha, self.eps, self.phi, ff.lo,
                         np.array(ff.local(ff.x)), np.array(ff.diam_rows), meta,
                         frozenset(self.row_meta))

    def packing_for_file(self):
        """The whole current configuration as a Packing on every rank (collective: a gather,
        for tests and callers that want it; the protocol and its files use ``state_rows``)."""
        return self.state_rows().packing()

    @property
    def pack(self):
        """``packing_for_file()`` (collective): the whole current configuration."""
        return self.packing_for_file()

    def _resume(self, call):
        """The MinimiseState of minimisation ``call`` if a checkpoint caught it in progress
        (its positions are set: each rank reads its block rows of the snapshot), else None."""
        found = self.checkpoint.in_progress(call, self.ff)
        if found is None:
            return None
        earlier_calls, state = found
        self.ff.n_force_calls += earlier_calls  # those of the interrupted run
        self._log(f"resuming minimisation {call + 1} from its checkpoint (FIRE step "
                  f"{state.fire.step} of round {state.round})")
        return state

    def _replay(self, call, record):
        """A minimisation of an earlier run, from its checkpoint record (collective: each rank
        reads its block rows of the positions)."""
        self.L = record["L"]
        self.ff.set_box(self.L)
        self.checkpoint.replay_rows(call, self.ff)
        res = record["result"]
        self.total_fire += res.fire_steps
        self.total_newton += res.newton_steps
        self.ff.n_force_calls += record["force_calls"]
        return res

    def network(self):
        """The current state's contact network (parjam.pack.jamnet) from the force field's block
        rows, on the slabs: no rank gathers the positions for it (collective)."""
        ff = self.ff
        return jamnet.build(self.comm, ff.local(ff.x), ff.diam_rows,
                            np.arange(ff.lo, ff.hi, dtype=np.int64), ff.L, self.alpha, self.eps)

    def pressure(self):
        return self.network().pressure

    def state(self, res, label, **info):
        return State(self.state_rows(), res, label, info)

    def stable_state(self, res, label, e_stop=-np.inf, phi=None, **info):
        """The State of the current minimum after ``stabilise``; its info records the check."""
        res, check = self.stabilise(res, e_stop, phi)
        return State(self.state_rows(), res, label, {**info, **check})

    def stabilise(self, res, e_stop=-np.inf, phi=None):
        """Make the current minimum (at volume fraction ``phi``, default the current one) a
        stable one (parjam.pack.stability): while the full Hessian of the non-rattlers has a negative
        curvature, or Nc < Nc_iso, move the packing out of the saddle along its softest
        direction (``escape``); where that fails, a compression cycle (``compression_cycle``,
        factors CYCLE_FACTORS in turn, each followed by the directional escapes again).
        Bounded and deterministic in the positions, so a run resumed from a checkpoint repeats
        it.  Returns the last MinResult and the record {"negative_curvatures_found",
        "excess_found", "escapes", "cycles", "negative_curvatures", "stable",
        "curvature_shift", "lowest_curvature_found"}; a state that stays unstable is returned
        flagged (stable = 0), never dropped: the state the directional escapes left (a failed
        cycle is undone)."""
        with log_stage("pack: stability"):
            phi = self.phi if phi is None else phi
            net = self.network()
            tol = self.balance_tol(net)
            if res.ok and net.max_force > tol:
                res = self.polish(res, tol)
                net = self.network()
            first = stability.check(self.comm, net)
            res, cur, escapes, lowest = self.escape(res, first, net, e_stop)
            cycles = 0
            for factor in CYCLE_FACTORS:
                if cur.stable or not cur.decided or res.status == "unjammed" \
                        or cur.n_active == 0:
                    break
                kept = (self.ff.x.copy(), self.L, res, cur)  # block rows
                cycles += 1
                res, cur = self.compression_cycle(phi, factor, e_stop)
                if not cur.stable and res.status != "unjammed" and cur.n_active > 0:
                    res, cur, more, _ = self.escape(res, cur, self.network(), e_stop)
                    escapes += more
                if not cur.stable:  # undo the cycle: the flagged state is the escapes' one
                    x, self.L, res, cur = kept
                    self.ff.set_box(self.L)
                    x.copy(self.ff.x)
                kept[0].destroy()
        if not cur.decided:
            self._log(f"stability undecided (left as it is, flagged): {cur.why}")
        elif not cur.stable:
            self._log(f"state still unstable after {escapes} escape(s) and {cycles} compression "
                      f"cycle(s): {cur.n_negative} negative curvature(s), Nc - Nc_iso = "
                      f"{cur.excess}")
        return res, {"negative_curvatures_found": first.n_negative,
                     "excess_found": first.excess, "escapes": escapes, "cycles": cycles,
                     "negative_curvatures": cur.n_negative, "stable": int(cur.stable),
                     "curvature_shift": cur.shift, "lowest_curvature_found": lowest}

    def escape(self, res, cur, net, e_stop=-np.inf):
        """Leave a saddle along its softest direction (``stability.escape_candidates``: to where
        the first new contact closes, on either side, or to the lowest energy along it) and
        minimise again; the first candidate that is stable is kept, else the search goes on
        from the last one, at most MAX_ESCAPES minimisations.  Returns (MinResult, Curvature,
        escapes, lowest curvature found)."""
        lowest, escapes = np.nan, 0
        while not cur.stable and cur.decided and escapes < MAX_ESCAPES and cur.n_active > 0:
            direction, lam = stability.softest_direction(self.comm, net, cur)
            lowest = lam if escapes == 0 else lowest
            if direction is None:
                break
            self._log(f"saddle: {cur.n_negative} negative curvature(s) (lowest {lam:.2e}), "
                      f"Nc - Nc_iso = {cur.excess}: escape {escapes + 1}")
            saddle = net.state  # the candidates' positions: owned rows of the saddle
            for t in stability.escape_candidates(net, direction)[:MAX_ESCAPES - escapes]:
                self.ff.set_rows(saddle.ids, stability.moved(saddle, direction, t))
                res = self.relax(None, e_stop)
                if res.ok:
                    res = self.polish(res, self.balance_tol(self.network()))
                escapes += 1
                if res.status == "unjammed":
                    break
                net = self.network()
                cur = stability.check(self.comm, net)
                if cur.stable:
                    break
            if res.status == "unjammed":
                break
        return res, cur, escapes, lowest

    def compression_cycle(self, phi, factor, e_stop=-np.inf):
        """Compress the state at volume fraction ``phi`` to ``factor`` times its distance to
        jamming (its virial dphi, ``virial_dphi``), minimise, decompress back to ``phi`` and
        minimise (to the balance of ``relax_balanced``): the compressed network closes the
        near-contacts that left the state a saddle, and keeps them on the way back where the
        directional escapes could not find them (measured: N = 1024, dphi = 1e-9 .. 1e-8,
        docs/explanation/reliability.md).  Returns (MinResult, Curvature) at ``phi``."""
        dphi = self.virial_dphi()
        self._log(f"compression cycle: to {factor:g} x dphi = {factor * dphi:.2e} and back")
        self.relax(phi + (factor - 1.0) * dphi)
        res = self.relax_balanced(phi, e_stop)
        if res.status == "unjammed":
            return res, stability.Curvature(-1, 0.0, 0, 0)
        return res, stability.check(self.comm, self.network())

    def virial_dphi(self):
        """phi - phi_c of the current state by the virial relation of its own contact network,
        alpha E phi / (p V) (O'Hern et al. 2003)."""
        net = self.network()
        return self._virial_excess(net.energy, net.pressure)

    def relax_balanced(self, phi=None, e_stop=-np.inf, newton_first=False):
        """``relax``, then on to ``balance_tol`` where --ftol is loose against the contact forces
        (near jamming, and for alpha > 2 whose forces ~dphi^(alpha-1) fall below --ftol)."""
        res = self.relax(phi, e_stop, newton_first=newton_first)
        if res.ok:
            res = self.polish(res, self.balance_tol(self.network()))
        return res

    def polish(self, res, tol):
        """Newton steps (parjam.pack.minimize.newton) from a converged minimum towards max|F| <= tol;
        bounded: Newton stops at the round-off floor of the forces, or at once where the
        Hessian is indefinite (a saddle, which ``stabilise`` then handles).  Deterministic in
        the positions, so a run resumed from a checkpoint repeats it exactly."""
        if not res.ok or res.fmax <= tol:
            return res
        before = self.ff.x.copy()
        nres = minimize.newton(self.ff, tol)
        self.total_newton += nres.newton_steps
        if not nres.fmax < res.fmax:  # no progress: keep the minimum as it was
            before.copy(self.ff.x)
            before.destroy()
            return res
        before.destroy()
        return minimize.MinResult("converged", nres.energy, nres.fmax, res.fire_steps,
                                  res.newton_steps + nres.newton_steps)

    def balance_tol(self, net):
        """Force tolerance of a returned state: --ftol, or REL_BALANCE of the mean contact force
        where that is tighter, floored at the forces' round-off level."""
        k = net.mean_stiffness if net.n_contacts else 1.0
        return min(self.settings.ftol, max(REL_BALANCE * net.mean_force, FORCE_FLOOR * k))

    def find_phi_c(self):
        """O'Hern bisection: returns the State whose E/N lies in [e_low, e_high]."""
        with log_stage("pack: phi_c bisection"):
            return self._find_phi_c()

    def _find_phi_c(self):
        s = self.settings
        n = self.n
        lo, hi = 0.0, np.inf
        step = s.first_step
        phi = self.phi
        for it in range(1, s.max_iter + 1):
            res = self.relax(phi, e_stop=s.e_low * n)
            e = res.energy / n
            self._log(f"phi_c search {it}: phi = {phi:.12f}, E/N = {e:.3e}, "
                      f"max|F| = {res.fmax:.2e} ({res.status})")
            if res.status == "not converged" and e >= s.e_low:
                raise ParjamError(f"minimisation did not converge at phi = {phi:.10f} "
                                  f"(max|F| = {res.fmax:.2e})", collective=False)
            if s.e_low <= e <= s.e_high:
                return self.stable_state(res, "phi_c", phi=phi, phi_c=phi,
                                         phi_bisection=phi, iterations=it)
            if e < s.e_low:
                lo = phi
                phi = phi + step if np.isinf(hi) else 0.5 * (lo + hi)
                step = min(2.0 * step, 0.02)
                if phi > PHI_MAX[self.d]:
                    raise UnjammedError(f"no jammed state below phi = {PHI_MAX[self.d]}: "
                                        f"E/N = {e:.3e} at phi = {lo:.10f}", collective=False)
            else:
                hi = phi
                guess = self._predict_phi(res.energy)
                if 0.0 < guess <= lo:
                    # this configuration jams below the old lower bound, which was found with an
                    # earlier configuration (the state changes along the search): drop it
                    lo = 0.0
                phi = guess if lo < guess < hi else 0.5 * (lo + hi)
            if hi - lo < 1e-13 * hi:
                # the bracket closed without a state in the window: its ends come from different
                # configurations (the state evolves along the search), so keep only the current
                # end and restart small steps from it
                lo, hi, step = (0.0, hi, step) if e > s.e_high else (lo, np.inf, 1e-9 * phi)
                phi = hi * (1.0 - 1e-9) if e > s.e_high else lo + step
        raise ParjamError(f"phi_c bisection did not land in the energy window after "
                          f"{s.max_iter} steps (bracket {lo:.14f}..{hi:.14f})", collective=False)

    def find_phi_c_from_above(self, dphi_stop, ratio=10.0):
        """phi_c by decompression and extrapolation, for sizes where the bisection is too slow.

        From a jammed minimum at phi, the virial relation of a fixed contact network gives the
        distance to jamming, phi - phi_c = alpha E phi / (p V) (E ~ dphi^alpha, p ~ dphi^(alpha-1),
        O'Hern et al. 2003).  Each step decompresses to phi_c,est + max(dphi_stop, dphi_est/ratio)
        and re-minimises from the previous minimum (few rearrangements per step), until the
        estimate is within a factor 1.5 of dphi_stop; phi_c is then the last extrapolation.
        Returns the State reached (about dphi_stop above phi_c)."""
        with log_stage("pack: phi_c extrapolation"):
            return self._find_phi_c_from_above(dphi_stop, ratio)

    def _jammed_start(self):
        """Minimise at the current phi, compressing by 0.01 until the packing is jammed."""
        phi = self.phi
        while True:
            res = self.relax(phi, e_stop=self.settings.e_low * self.n)
            if res.status != "unjammed":
                return res
            phi += 0.01
            if phi > PHI_MAX[self.d]:
                break
        raise UnjammedError(f"no jammed state below phi = {PHI_MAX[self.d]}",
                            collective=False)

    def _find_phi_c_from_above(self, dphi_stop, ratio):
        res = self._jammed_start()
        if not res.ok:
            raise ParjamError(f"minimisation did not converge at phi = {self.phi:.10f} "
                              f"(max|F| = {res.fmax:.2e})", collective=False)
        found = self._refine(dphi_stop, ratio, self.settings.max_iter, tol=None, res=res)
        return State(self.state_rows(), found.pop("result"), "phi_c,est",
                     {**found, "dphi_est": found["dphi_reached"],
                      "phi_c_method": "virial extrapolation from above"})

    def refine_phi_c(self, dphi_stop, ratio=REFINE_RATIO, max_steps=10):
        """Refine phi_c from the current jammed minimum by the virial relation of its contact
        network, phi_c = phi - alpha E phi / (p V) (O'Hern et al. 2003; E ~ dphi^alpha,
        p ~ dphi^(alpha-1)): decompress to phi_c,est + max(dphi_stop, dphi_est / ratio) (below
        dphi_stop: dphi_est / ratio), re-minimise, estimate again, until the last state lies
        within 1.5 dphi_stop of phi_c and the last two estimates agree to 1 % of dphi_stop.
        Their difference is the resolution of phi_c.  Returns {"phi_c", "phi_c_resolution",
        "phi_c_estimates", "dphi_reached"}; the packing is left at the last state."""
        with log_stage("pack: phi_c refinement"):
            found = self._refine(dphi_stop, ratio, max_steps, tol=0.2 * RESOLVED_FRACTION)
            found.pop("result")
            return found

    def _refine(self, dphi_stop, ratio, max_steps, tol, res=None):
        """The loop of ``refine_phi_c``; ``tol`` None: stop at the first state within
        1.5 dphi_stop once there are two estimates (the extrapolation protocol's cost)."""
        estimates = []
        jammed_phi = self.phi
        for it in range(1, max_steps + 1):
            net = self.network()
            energy = net.energy
            excess = self._virial_excess(energy, net.pressure)
            phi = self.phi
            estimates.append(phi - excess)
            change = abs(estimates[-1] - estimates[-2]) if len(estimates) > 1 else np.inf
            self._log(f"phi_c refinement {it}: phi = {phi:.14f}, dphi_est = {excess:.3e}, "
                      f"phi_c,est = {estimates[-1]:.14f} (change {change:.1e})")
            near = excess <= 1.5 * dphi_stop
            if near and len(estimates) > 1 and (tol is None or change <= tol * dphi_stop):
                break
            if it == max_steps:
                break
            dphi = excess / ratio if near else max(dphi_stop, excess / ratio)
            target = estimates[-1] + dphi
            e_stop = 1e-3 * energy * (dphi / excess) ** self.alpha
            res = self.relax_balanced(target, e_stop=e_stop)
            if res.status == "unjammed" or self.network().n_active == 0:
                # the network changed on the way (or only rattlers keep a few overlaps, forces
                # below --ftol: alpha > 2): back to jammed_phi, smaller steps
                res = self.relax_balanced(jammed_phi)
                ratio = max(2.0, ratio / 3.0)
            if not res.ok:
                raise ParjamError(f"minimisation did not converge at phi = {self.phi:.10f} "
                                  f"(max|F| = {res.fmax:.2e})", collective=False)
            jammed_phi = self.phi
        resolution = max(change, PHI_C_ROUNDOFF * self.phi)
        return {"phi_c": estimates[-1], "phi_c_resolution": resolution, "iterations": it,
                "phi_c_estimates": np.array(estimates), "dphi_reached": excess, "result": res}

    def _virial_excess(self, energy, p=None):
        """phi - phi_c = alpha E phi / (p V) of a jammed state with a fixed contact network
        (``p``: its pressure, default the current state's)."""
        p = self.pressure() if p is None else p
        if p <= 0 or energy <= 0:
            raise UnjammedError(f"no pressure at phi = {self.phi:.10f}", collective=False)
        return self.alpha * energy * self.phi / (p * self.volume)

    def _predict_phi(self, energy):
        """Volume fraction where E/N reaches the middle of the window, from the virial relation
        E/(dE/dphi) = (phi - phi_c)/alpha of a jammed state with a fixed contact network."""
        s = self.settings
        try:
            excess = self._virial_excess(energy)
        except UnjammedError:
            return -1.0
        phi = self.phi
        target = 0.5 * (s.e_low + s.e_high) * self.n
        return phi - excess + excess * (target / energy) ** (1.0 / self.alpha)

    def at_phi(self, phi, label, e_stop=None, newton_first=False, **info):
        """Minimised, stable (``stabilise``) state at volume fraction phi; UnjammedError if the
        energy falls below ``e_stop`` (default: 1e-6 of the low end of the energy window)."""
        e_stop = self.settings.e_low * self.n * 1e-6 if e_stop is None else e_stop
        res = self.relax_balanced(phi, e_stop=e_stop, newton_first=newton_first)
        if res.status == "unjammed" or (res.ok and self.network().n_active == 0):
            raise UnjammedError(f"unjammed at phi = {phi:.10f}: energy per particle reached "
                                f"{res.energy / self.n:.3e}", collective=False)
        if not res.ok:
            raise ParjamError(f"minimisation did not converge at phi = {phi:.10f} "
                              f"(max|F| = {res.fmax:.2e})", collective=False)
        return self.stable_state(res, label, e_stop, phi=phi, **info)

    def energy_floor(self, dphi):
        """An energy far below that of a jammed state at phi_c + dphi (overlaps ~dphi / (2 d),
        z/2 ~ d contacts per particle), above which the state counts as jammed: the window's
        1e-6 floor, lowered for dphi below ~1e-8 where E/N itself is below it."""
        d, a = self.d, self.alpha
        expected = self.n * d * (dphi / (2.0 * d)) ** a / a
        return min(self.settings.e_low * self.n * 1e-6, 1e-4 * expected)

    def ladder(self, phi_c, dphis, direction="compress"):
        """States at phi_c + dphi, compressing upwards or decompressing from the largest."""
        with log_stage("pack: dphi ladder"):
            return self._ladder(phi_c, dphis, direction)

    def _ladder(self, phi_c, dphis, direction):
        order = sorted(dphis) if direction == "compress" else sorted(dphis, reverse=True)
        out = []
        for k, dphi in enumerate(order):
            self._log(f"dphi step {k + 1}/{len(order)}: dphi = {dphi:.1e}")
            before = self.state_rows()  # the last jammed state: this rank's rows, O(N/P)
            info = {"dphi": dphi, "phi_c": phi_c, "ladder": direction}
            try:
                st = self.at_phi(phi_c + dphi, f"dphi{dphi:.1e}",
                                 e_stop=self.energy_floor(dphi), **info)
            except UnjammedError as exc:
                self._log(f"dphi = {dphi:.1e} unjammed ({exc}): again from the last jammed "
                          f"state, in {REJAM_STEPS} smaller steps, each minimised by Newton "
                          f"first")
                try:
                    st = self.rejam(before, f"dphi{dphi:.1e}", **info)
                except UnjammedError as again:
                    raise LadderUnjammed(f"ladder step {k + 1} of {len(order)} (dphi = "
                                         f"{dphi:.1e}) unjammed, also in {REJAM_STEPS} smaller "
                                         f"steps with Newton: {again}", out, dphi) from None
            st.info["dphi_virial"] = self._virial_excess(st.result.energy)
            out.append(st)
        return out

    def restore(self, rows):
        """Go back to a state made before (its StateRows: positions and box; the diameters
        never change)."""
        self.L = rows.L
        self.ff.set_box(rows.L)
        self.ff.local(self.ff.x)[:] = rows.x

    def rejam(self, before, label, *, phi_c, dphi, **info):
        """A ladder step that unjammed, made again from the last jammed state ``before``: the
        way from its distance to jamming to ``dphi`` cut into REJAM_STEPS geometric sub-steps
        (linear where they cross zero), each minimised by damped Newton first, so that no
        momentum carries the packing out of its basin (FIRE's can: it overshoots across a
        saddle into a configuration jamming at another phi_c).  The state at phi_c + dphi gets
        the same balance and stability check as any; ``rejammed`` = 1 in its info.  Raises
        UnjammedError if it unjams again (the member then truly unjams there)."""
        self.restore(before)
        start = before.phi - phi_c
        e_stop = self.energy_floor(dphi)
        if start > 0 and dphi > 0:
            steps = [start * (dphi / start) ** (s / REJAM_STEPS) for s in range(1, REJAM_STEPS)]
        else:
            steps = [start + (dphi - start) * s / REJAM_STEPS for s in range(1, REJAM_STEPS)]
        for k, sub in enumerate(steps):
            # each sub-step a stable state (the escapes of ``stabilise`` follow an instability
            # of the stress term down its softest mode, gently, where a big step jumped)
            mid = self.at_phi(phi_c + sub, label, e_stop=min(e_stop, self.energy_floor(abs(sub))),
                              newton_first=True)
            self._log(f"  sub-step {k + 1}/{REJAM_STEPS}: dphi = {sub:.2e}, stable "
                      f"{mid.info.get('stable', 1)}, E/N = {mid.result.energy / self.n:.3e}")
        st = self.at_phi(phi_c + dphi, label, e_stop=e_stop, newton_first=True, phi_c=phi_c,
                         dphi=dphi, **info)
        st.info["rejammed"] = 1
        return st

    def at_pressure(self, p_target, phi_c):
        """Volume fraction where the minimised pressure equals p_target (relative ptol):
        secant iterations on p^(1/(alpha-1)), which is linear in phi near jamming."""
        with log_stage("pack: target pressure"):
            return self._at_pressure(p_target, phi_c)

    def _at_pressure(self, p_target, phi_c):
        s = self.settings
        expo = 1.0 / (self.alpha - 1.0)
        g_t = p_target**expo
        pts = [(phi_c, 0.0)]
        phi = phi_c + g_t  # first guess: p ~ dphi^(alpha-1) with unit prefactor
        for it in range(1, s.max_iter + 1):
            st = self.at_phi(phi, f"p{p_target:.1e}", phi_c=phi_c, target_pressure=p_target)
            p = self.pressure()
            self._log(f"pressure search {it}: phi = {phi:.12f}, p = {p:.6e} (target {p_target:.3e})")
            if abs(p / p_target - 1.0) <= s.ptol:
                st.info["iterations"] = it
                return st
            pts.append((phi, p**expo))
            (x0, g0), (x1, g1) = pts[-2], pts[-1]
            phi = x1 + (g_t - g1) * (x1 - x0) / (g1 - g0) if g1 != g0 else x1 * (1 + 1e-6)
        raise ParjamError(f"pressure {p_target:g} not reached in {s.max_iter} steps",
                          collective=False)

    def destroy(self):
        self.ff.destroy()


def make_jammed(d, n, dphis, seed=0, member=0, dispersity=None, ratio=DEFAULT_RATIO,
                alpha=DEFAULT_ALPHA, comm=None, phi_start=None, settings=None):
    """Packings of one configuration at phi_c + dphi for each dphi (ascending), and phi_c
    (bisection, then ``refine_phi_c`` down to the smallest dphi).

    The same (seed, member) gives the same configuration as ``parjam pack``.  ``comm`` defaults
    to COMM_SELF, so every rank builds the same packing (handy in tests and scripts).
    """
    PETSc = env.petsc()
    comm = PETSc.COMM_SELF if comm is None else comm
    dispersity = dispersity or DEFAULT_DISPERSITY[d]
    phi0 = phi_start or DEFAULT_PHI_START[d]
    jam = Jammer(comm, start_rows(comm, d, n, phi0, alpha, dispersity, ratio,
                                  member_rng(seed, member)), settings)
    try:
        jam.find_phi_c()  # the bisection, then the refinement from the jammed side
        phi_c = jam.refine_phi_c(min(dphis) if len(dphis) else 1e-6)["phi_c"]
        states = jam.ladder(phi_c, list(dphis)) if len(dphis) else []
    finally:
        jam.destroy()
    out = [s.pack for s in states]
    for s, p in zip(states, out):
        p.meta.update(s.info)
    return phi_c, out
