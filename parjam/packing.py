"""Jammed packings: random (infinite-temperature) starts, the O'Hern bisection to phi_c, the
dphi ladder (compression up from phi_c, or decompression down to it) and target pressures.

O'Hern, Silbert, Liu & Nagel, PRE 68, 011306 (2003): a configuration is compressed or
decompressed and re-minimised until its energy per particle lies in a tiny window above zero;
the volume fraction there is its phi_c.  The step in phi is chosen by bisection of the bracket
[unjammed, overjammed], accelerated (and always kept inside the bracket) by the prediction of
the virial relation for a jammed state, E ~ (phi - phi_c)^alpha, dE/dphi = p V / phi, which gives
phi_c ~= phi - alpha E phi / (p V) while the contact network does not change.
"""

from dataclasses import dataclass, field

import numpy as np

from parjam import env, minimize
from parjam.errors import ParjamError, UnjammedError
from parjam.forces import ForceField
from parjam.logstage import log_stage
from parjam.network import analyze
from parjam.protocol import (DEFAULT_ALPHA, DEFAULT_DISPERSITY, DEFAULT_ENERGY_WINDOW,
                             DEFAULT_FTOL, DEFAULT_PHI_START, DEFAULT_RATIO)
from parjam.system import Packing, sphere_volume

DISPERSITIES = ("mono", "bi", "poly")
PHI_MAX = {2: 0.99, 3: 0.9}  # the phi_c search gives up above these (nothing jams so late)


def diameters(n, dispersity="mono", ratio=DEFAULT_RATIO, rng=None):
    """Diameters with the smallest equal to 1: mono; bi (50:50, large/small = ratio); poly
    (uniform between 1 and ratio)."""
    if dispersity == "mono":
        return np.ones(n), np.zeros(n, dtype=np.int32)
    if not np.isfinite(ratio) or ratio < 1.0:
        raise ParjamError(f"diameter ratio must be >= 1, got {ratio}")
    if dispersity == "bi":
        species = (np.arange(n) >= n // 2).astype(np.int32)
        return np.where(species == 1, ratio, 1.0), species
    if dispersity == "poly":
        return 1.0 + (ratio - 1.0) * rng.random(n), np.zeros(n, dtype=np.int32)
    raise ParjamError(f"unknown dispersity {dispersity!r}; choose from {', '.join(DISPERSITIES)}")


def member_rng(seed, member):
    """Independent, reproducible stream for member m, whatever the number of ranks."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(member)]))


def random_packing(d, n, phi, alpha=DEFAULT_ALPHA, dispersity="mono", ratio=DEFAULT_RATIO,
                   rng=None):
    """Uniform random positions at volume fraction phi: an infinite-temperature configuration."""
    rng = rng if rng is not None else np.random.default_rng()
    diam, species = diameters(n, dispersity, ratio, rng)
    L = float((sphere_volume(diam, d).sum() / phi) ** (1.0 / d))
    pos = rng.uniform(0.0, L, size=(n, d))
    pos[pos >= L] = 0.0
    order = spatial_order(pos, L, 2.0 * diam.max())
    return Packing(pos[order], diam[order], L, alpha, meta={"species": species[order]})


def spatial_order(pos, L, cell):
    """Permutation that numbers the particles cell by cell (cells of edge >= ``cell``, in
    lexicographic order): neighbours get nearby indices, so the force kernel and the matrices
    touch nearby memory, and the contiguous row blocks of the MPI ranks are compact slabs with
    few couplings between ranks.  A 3D N = 10^5 force evaluation costs 12 ms instead of 21 ms in
    random order.  The particles are independent and identically placed, so this is the same
    random configuration."""
    m = max(1, int(L // cell))
    idx = np.minimum((pos / L * m).astype(np.int64), m - 1)
    key = np.zeros(len(pos), dtype=np.int64)
    for k in range(pos.shape[1]):
        key = key * m + idx[:, k]
    return np.argsort(key, kind="stable")


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
    """One minimised state of a configuration."""

    pack: Packing
    result: minimize.MinResult
    label: str
    info: dict = field(default_factory=dict)


class Jammer:
    """Minimises one configuration at chosen volume fractions on communicator ``comm``."""

    def __init__(self, comm, pack, settings=None, progress=None, checkpoint=None):
        self.comm = comm
        self.settings = settings or JamSettings()
        self.progress = progress
        self.checkpoint = checkpoint  # parjam.checkpoint.Checkpoint, or None
        self.calls = 0  # minimisations so far: the key of their checkpoint records
        self.ff = ForceField(comm, pack.diam, pack.L, pack.d, pack.alpha, pack.eps)
        self.pack = pack.copy()
        self.ff.set_positions(self.pack.pos)
        self.total_fire = 0
        self.total_newton = 0
        # minimiser steps: a line every 10 s at most (only long minimisations show them)
        throttled = getattr(progress, "throttled", None)
        self._inner = throttled(10.0) if throttled is not None else None

    def _log(self, msg):
        if self.progress is not None:
            self.progress(msg)

    def relax(self, phi=None, e_stop=-np.inf):
        """Rescale affinely to phi (if given) and minimise; returns the MinResult.  With a
        checkpoint, a minimisation finished in an earlier run is replayed from its record and an
        interrupted one continues from its last snapshot."""
        call, ck = self.calls, self.checkpoint
        self.calls += 1
        record = ck.finished(call) if ck is not None else None
        if record is not None and phi is not None and record["L"] != self.pack.box_for_phi(phi):
            self._log(f"checkpoint record {call + 1} is at another volume fraction than this "
                      f"protocol asks for: recomputing from there")
            ck.discard_from(call)
            record = None
        if record is not None:
            return self._replay(record)
        if phi is not None:
            self.pack = self.pack.rescaled(phi)
            self._set_state(self.pack.pos, self.pack.L)
        calls_before = self.ff.n_force_calls
        resume = self._resume(call) if ck is not None else None
        hook = ck.snapshot(call, self.ff, self.pack.L, calls_before) if ck is not None else None
        try:
            res = minimize.minimize(self.ff, self.settings.ftol, e_stop,
                                   fire_rel=self.settings.fire_rel, progress=self._inner,
                                   snapshot=hook, resume=resume)
        except ValueError as exc:  # e.g. a box too small for the neighbour search
            raise ParjamError(f"at phi = {self.pack.phi:.10f}: {exc}", collective=False) from None
        self.total_fire += res.fire_steps
        self.total_newton += res.newton_steps
        self.pack.pos = np.array(self.ff.gather())
        if ck is not None:
            ck.finish(call, self.pack, res, self.ff.n_force_calls - calls_before)
        return res

    def _resume(self, call):
        """The MinimiseState of minimisation ``call`` if a checkpoint caught it in progress
        (its positions are set), else None."""
        found = self.checkpoint.in_progress(call)
        if found is None:
            return None
        pos, earlier_calls, state = found
        self.ff.set_positions(pos)
        self.ff.n_force_calls += earlier_calls  # those of the interrupted run
        self._log(f"resuming minimisation {call + 1} from its checkpoint (FIRE step "
                  f"{state.fire.step} of round {state.round})")
        return state

    def _set_state(self, pos, L):
        """Box and positions of the force field (a new box drops the neighbour list)."""
        self.ff.set_box(L)
        self.ff.set_positions(pos)

    def _replay(self, record):
        """A minimisation of an earlier run, from its checkpoint record."""
        self.pack.pos, self.pack.L = record["pos"].copy(), record["L"]
        self._set_state(self.pack.pos, self.pack.L)
        res = record["result"]
        self.total_fire += res.fire_steps
        self.total_newton += res.newton_steps
        self.ff.n_force_calls += record["force_calls"]
        return res

    def pressure(self):
        return analyze(self.pack).pressure

    def state(self, res, label, **info):
        return State(self.pack.copy(), res, label, info)

    def find_phi_c(self):
        """O'Hern bisection: returns the State whose E/N lies in [e_low, e_high]."""
        with log_stage("pack: phi_c bisection"):
            return self._find_phi_c()

    def _find_phi_c(self):
        s = self.settings
        n = self.pack.n
        lo, hi = 0.0, np.inf
        step = s.first_step
        phi = self.pack.phi
        for it in range(1, s.max_iter + 1):
            res = self.relax(phi, e_stop=s.e_low * n)
            e = res.energy / n
            self._log(f"phi_c search {it}: phi = {phi:.12f}, E/N = {e:.3e}, "
                      f"max|F| = {res.fmax:.2e} ({res.status})")
            if res.status == "not converged" and e >= s.e_low:
                raise ParjamError(f"minimisation did not converge at phi = {phi:.10f} "
                                  f"(max|F| = {res.fmax:.2e})", collective=False)
            if s.e_low <= e <= s.e_high:
                return self.state(res, "phi_c", phi_c=phi, iterations=it)
            if e < s.e_low:
                lo = phi
                phi = phi + step if np.isinf(hi) else 0.5 * (lo + hi)
                step = min(2.0 * step, 0.02)
                if phi > PHI_MAX[self.pack.d]:
                    raise UnjammedError(f"no jammed state below phi = {PHI_MAX[self.pack.d]}: "
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
        phi = self.pack.phi
        while True:
            res = self.relax(phi, e_stop=self.settings.e_low * self.pack.n)
            if res.status != "unjammed":
                return res
            phi += 0.01
            if phi > PHI_MAX[self.pack.d]:
                break
        raise UnjammedError(f"no jammed state below phi = {PHI_MAX[self.pack.d]}",
                            collective=False)

    def _find_phi_c_from_above(self, dphi_stop, ratio):
        s = self.settings
        res = self._jammed_start()
        jammed_phi = self.pack.phi
        for it in range(1, s.max_iter + 1):
            if not res.ok:
                raise ParjamError(f"minimisation did not converge at phi = {self.pack.phi:.10f} "
                                  f"(max|F| = {res.fmax:.2e})", collective=False)
            phi = self.pack.phi
            excess = self._virial_excess(res.energy)
            phi_c = phi - excess
            self._log(f"phi_c extrapolation {it}: phi = {phi:.12f}, dphi_est = {excess:.3e}, "
                      f"phi_c,est = {phi_c:.12f}")
            if excess <= 1.5 * dphi_stop:
                return self.state(res, "phi_c,est", phi_c=phi_c, dphi_est=excess, iterations=it,
                                  phi_c_method="virial extrapolation from above")
            target = phi_c + max(dphi_stop, excess / ratio)
            res = self.relax(target, e_stop=s.e_low * self.pack.n * 1e-6)
            if res.status == "unjammed":  # overshot (the network changed): back half way
                res = self.relax(0.5 * (target + jammed_phi))
                ratio = max(2.0, ratio / 2.0)
            jammed_phi = self.pack.phi
        raise ParjamError(f"phi_c extrapolation did not reach dphi = {dphi_stop:g} in "
                          f"{s.max_iter} steps", collective=False)

    def _virial_excess(self, energy):
        """phi - phi_c = alpha E phi / (p V) of a jammed state with a fixed contact network."""
        p = self.pressure()
        if p <= 0 or energy <= 0:
            raise UnjammedError(f"no pressure at phi = {self.pack.phi:.10f}", collective=False)
        return self.pack.alpha * energy * self.pack.phi / (p * self.pack.volume)

    def _predict_phi(self, energy):
        """Volume fraction where E/N reaches the middle of the window, from the virial relation
        E/(dE/dphi) = (phi - phi_c)/alpha of a jammed state with a fixed contact network."""
        s = self.settings
        try:
            excess = self._virial_excess(energy)
        except UnjammedError:
            return -1.0
        phi = self.pack.phi
        target = 0.5 * (s.e_low + s.e_high) * self.pack.n
        return phi - excess + excess * (target / energy) ** (1.0 / self.pack.alpha)

    def at_phi(self, phi, label, **info):
        """Minimised state at volume fraction phi; UnjammedError if the energy vanishes."""
        res = self.relax(phi, e_stop=self.settings.e_low * self.pack.n * 1e-6)
        if res.status == "unjammed":
            raise UnjammedError(f"unjammed at phi = {phi:.10f}: energy per particle reached "
                                f"{res.energy / self.pack.n:.3e}", collective=False)
        if not res.ok:
            raise ParjamError(f"minimisation did not converge at phi = {phi:.10f} "
                              f"(max|F| = {res.fmax:.2e})", collective=False)
        return self.state(res, label, **info)

    def ladder(self, phi_c, dphis, direction="compress"):
        """States at phi_c + dphi, compressing upwards or decompressing from the largest."""
        with log_stage("pack: dphi ladder"):
            return self._ladder(phi_c, dphis, direction)

    def _ladder(self, phi_c, dphis, direction):
        order = sorted(dphis) if direction == "compress" else sorted(dphis, reverse=True)
        out = []
        for k, dphi in enumerate(order):
            self._log(f"dphi step {k + 1}/{len(order)}: dphi = {dphi:.1e}")
            st = self.at_phi(phi_c + dphi, f"dphi{dphi:.1e}", dphi=dphi, phi_c=phi_c,
                             ladder=direction)
            out.append(st)
        return out

    def at_pressure(self, p_target, phi_c):
        """Volume fraction where the minimised pressure equals p_target (relative ptol):
        secant iterations on p^(1/(alpha-1)), which is linear in phi near jamming."""
        with log_stage("pack: target pressure"):
            return self._at_pressure(p_target, phi_c)

    def _at_pressure(self, p_target, phi_c):
        s = self.settings
        expo = 1.0 / (self.pack.alpha - 1.0)
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
    """Packings of one configuration at phi_c + dphi for each dphi (ascending), and phi_c.

    The same (seed, member) gives the same configuration as ``parjam pack``.  ``comm`` defaults
    to COMM_SELF, so every rank builds the same packing (handy in tests and scripts).
    """
    PETSc = env.petsc()
    comm = PETSc.COMM_SELF if comm is None else comm
    dispersity = dispersity or DEFAULT_DISPERSITY[d]
    phi0 = phi_start or DEFAULT_PHI_START[d]
    pack = random_packing(d, n, phi0, alpha, dispersity, ratio, member_rng(seed, member))
    jam = Jammer(comm, pack, settings)
    try:
        phic = jam.find_phi_c()
        phi_c = phic.info["phi_c"]
        states = jam.ladder(phi_c, list(dphis)) if len(dphis) else []
    finally:
        jam.destroy()
    out = [s.pack for s in states]
    for s, p in zip(states, out):
        p.meta.update(s.info)
    return phi_c, out
