"""The states of one ensemble member of ``parjam pack`` (its protocol: phi_c search, then the
ladder, the target pressures or a quench) and the flags that say when a state is not what it
seems (resolution of phi_c, the virial dphi, force balance, crystallisation, stability).
Writing them is parjam.study.members'."""

import sys

import numpy as np

from parjam.errors import UnjammedError
from parjam.progress import member as member_name
from parjam.net import order
from parjam.pack import staterows
from parjam.pack.packing import RESOLVED_FRACTION, JamSettings, Jammer, LadderUnjammed
from parjam.pack.randomstart import member_rng, start_rows


def settings_from(args):
    lo, hi = args.energy_window
    return JamSettings(ftol=args.ftol, e_low=lo, e_high=hi)


def member_states(args, member, comm, progress, checkpoint=None, start=None):
    """Every requested state of one member, in the order they are computed.  ``start``: this
    rank's block rows of the configuration to start from (parjam.pack.filestart.start_rows for
    ``pack --from``); None for the member's random start."""
    if start is None:  # this rank's block rows of the random start: no rank makes all N
        rng = member_rng(args.seed, member)
        start_phi = args.phi if args.phi is not None else args.phi_start
        start = start_rows(comm, args.dim, args.n, start_phi, args.alpha, args.dispersity,
                           args.ratio, rng)
    jammer = Jammer(comm, start, settings_from(args), progress, checkpoint)
    del start  # the Jammer keeps its block rows only
    stopped = None
    try:
        if args.phi is not None:
            states = [jammer.at_phi(args.phi, f"phi{args.phi:.4f}")]
            protocol = "quench"
        else:
            phi_c, states, search, resolution = find_phi_c(jammer, args, progress)
            try:
                if args.pressure:
                    protocol = f"{search}+pressure"
                    for p in sorted(args.pressure):
                        try:
                            states.append(jammer.at_pressure(p, phi_c))
                        except UnjammedError as exc:
                            raise LadderUnjammed(f"target pressure {p:.1e} unjammed: {exc}",
                                                 [], p) from None
                else:
                    protocol = f"{search}+ladder"
                    states += jammer.ladder(phi_c, args.dphi, args.ladder)
            except LadderUnjammed as exc:  # keep the jammed states made before that step
                states += exc.states
                stopped = exc
                for st in states:
                    st.info["ladder_unjammed_at"] = exc.step
            resolution_flags(states, resolution, f"{member_name(member)} ",
                             speak=comm.getRank() == 0)
            virial_flags(states)
        totals = {"fire_steps": jammer.total_fire, "newton_steps": jammer.total_newton,
                  "force_evaluations": jammer.ff.n_force_calls}
    finally:
        jammer.destroy()
    return states, protocol, totals, stopped


def smallest_dphi(args):
    """The smallest distance to phi_c the protocol asks for: its smallest dphi, or for target
    pressures p ~ dphi^(alpha-1) with a prefactor of order one."""
    if args.pressure:
        return min(p ** (1.0 / (args.alpha - 1.0)) for p in args.pressure)
    return min(args.dphi)


def find_phi_c(jammer, args, progress):
    """(phi_c, [the phi_c state to write, if any], protocol name) by the chosen search; phi_c is
    refined from the jammed side (parjam.pack.packing.Jammer.refine_phi_c) and its resolution is
    recorded in every state and checked against the smallest requested dphi."""
    stop = smallest_dphi(args)
    if args.phic_method == "extrapolate":
        st = jammer.find_phi_c_from_above(stop)
        phi_c = st.info["phi_c"]
        progress(f"phi_c = {phi_c:.12f} +- {st.info['phi_c_resolution']:.1e} (extrapolated "
                 f"from dphi = {st.info['dphi_est']:.2e}) after {st.info['iterations']} "
                 f"minimisations")
        return phi_c, [], "virial-extrapolation", st.info["phi_c_resolution"]
    phic = jammer.find_phi_c()
    progress(f"bisection: phi = {phic.info['phi_c']:.12f} after {phic.info['iterations']} "
             f"minimisations")
    found = jammer.refine_phi_c(stop)
    phi_c, resolution = found["phi_c"], found["phi_c_resolution"]
    phic.info.update(phi_c=phi_c, phi_c_resolution=resolution,
                     phi_c_estimates=found["phi_c_estimates"],
                     dphi=phic.phi - phi_c)
    progress(f"phi_c = {phi_c:.12f} +- {resolution:.1e} (refined from the jammed side; the "
             f"bisection's state lies {phic.phi - phi_c:.2e} above it)")
    return phi_c, ([] if args.no_phic_file else [phic]), "ohern-bisection", resolution


def resolution_flags(states, resolution, label_prefix, speak=True):
    """Record the resolution of phi_c in every state and flag (file, and one line on stderr if
    ``speak``: the member's rank 0) each requested dphi that it does not resolve to
    RESOLVED_FRACTION."""
    for st in states:
        st.info["phi_c_resolution"] = resolution
        dphi = st.info.get("dphi")
        if dphi is None or st.label == "phi_c":
            continue
        ok = resolution <= RESOLVED_FRACTION * dphi
        st.info["dphi_resolved"] = int(ok)
        if not ok and speak:
            warn(f"{label_prefix}{st.label}: dphi = {dphi:.1e} is below what phi_c resolves "
                  f"(+- {resolution:.1e}; needs dphi >= {resolution / RESOLVED_FRACTION:.1e} for "
                  f"{RESOLVED_FRACTION:.0%}): its label is not reliable (dphi_resolved = 0 in "
                  f"the file)")


# a state's own distance to jamming (virial relation of its contact network) and its label
# phi - phi_c agree to DPHI_VIRIAL_TOL + DPHI_VIRIAL_SQRT * sqrt(dphi) (relative): the relation
# is exact for a fixed network, and drifts as compression adds contacts; measured over 16
# ladders (3D mono, 2D bi, N = 64, 256): < 3 % up to dphi = 1e-3 (2.9 % at 1e-10 after a
# compression cycle), 7.6 % at 1e-2, 11 % at 0.1.  A state further off re-jammed at another
# phi_c on the way (2D bi N = 256 seed 2: 93 % at 1e-4, and the 9.8 % shift it leaves at 1e-3).
DPHI_VIRIAL_TOL = 0.05
DPHI_VIRIAL_SQRT = 0.5


def state_network(st):
    """The contact network of a State, on the slabs from its rows (parjam.pack.staterows;
    collective)."""
    return st.rows.network()


def state_hexatic(st, net):
    """(local, global) hexatic order of a State (parjam.net.order's), from its rows
    (collective)."""
    return staterows.hexatic_order(st.rows, net)


def virial_dphi(st):
    """phi - phi_c of a State from its own contact network, alpha E phi / (p V) (the virial
    relation of parjam.pack.packing.Jammer.refine_phi_c); NaN without pressure.  Collective."""
    net = state_network(st)
    rows = st.rows
    if net.pressure <= 0 or net.energy <= 0:
        return np.nan
    return rows.alpha * net.energy * rows.phi / (net.pressure * rows.volume)


def virial_flags(states):
    """Record the virial dphi of every state with a phi_c and whether it agrees with its label
    phi - phi_c (``dphi_virial``, ``dphi_virial_ok``; ``stability_observables`` says so on
    stderr where it does not)."""
    for st in states:
        phi_c = st.info.get("phi_c")
        if phi_c is None:
            continue
        label = st.phi - phi_c
        found = virial_dphi(st)
        tol = virial_tolerance(label)
        st.info["dphi_virial"] = found
        st.info["dphi_virial_ok"] = int(bool(np.isfinite(found)
                                             and abs(found - label) <= tol * abs(label)))


def virial_tolerance(dphi):
    """Relative tolerance between a state's virial dphi and its label phi - phi_c."""
    return DPHI_VIRIAL_TOL + DPHI_VIRIAL_SQRT * np.sqrt(abs(dphi))


REL_FORCE_WARN = 1e-4  # max|F| / mean contact force above this: force balance is poor
# (harmonic phi_c states end near 1e-5: forces ~1e-8 against ftol = 1e-13; alpha = 3 at
# dphi = 1e-8 reaches 1.8e-3)


def quality_checks(pack, net, label, dphi=None, hexatic=None, speak=True):
    """Observables that flag a state which is not what it seems, each with a warning on stderr
    (where ``speak``): a crystallised 2D packing (hexatic order, parjam.net.order; ``hexatic`` its
    (local, global) values where known, else computed from ``pack``) and a force balance that
    is poor relative to the contact forces (e.g. alpha = 3 at dphi = 1e-8, where forces are
    ~1e-16 and the absolute --ftol means little)."""
    extra, warning = order.check(pack, net, dphi, hexatic)  # hexatic order and contact excess
    if warning and speak:
        warn(f"{label}: {warning}")
    rel = net.summary()["max_force_rel"]
    if rel > REL_FORCE_WARN and speak:
        warn(f"{label}: force balance only {rel:.1e} of the mean contact force "
              f"(max|F| = {net.max_force:.1e}, mean contact force {net.mean_force:.1e}): the "
              f"contact forces approach the round-off of the forces")
    return extra


STABILITY_KEYS = ("stable", "negative_curvatures", "negative_curvatures_found", "excess_found",
                  "escapes", "cycles", "curvature_shift", "lowest_curvature_found",
                  "dphi_virial", "dphi_virial_ok", "ladder_unjammed_at")


def stability_observables(st, label, speak=True):
    """/observables entries of the stability check (parjam.pack.packing.Jammer.stabilise), the virial
    dphi check (``virial_flags``) and, for a member whose ladder unjammed, the step that did;
    a state that could not be made a stable minimum is flagged (stable = 0) and said on
    stderr (where ``speak``)."""
    out = {k: st.info[k] for k in STABILITY_KEYS if k in st.info}
    if "dphi_virial_ok" in out:
        out["dphi_virial_ok"] = np.int8(out["dphi_virial_ok"])
        if not out["dphi_virial_ok"] and speak:
            label_dphi = st.phi - st.info["phi_c"]
            warn(f"{label}: its own contact network puts it at dphi = "
                  f"{st.info['dphi_virial']:.2e} from jamming (virial relation), not "
                  f"phi - phi_c = {label_dphi:.2e} (tolerance "
                  f"{virial_tolerance(label_dphi):.1%}): it re-jammed at another phi_c on the "
                  f"way (dphi_virial_ok = 0 in /observables)")
    if "stable" in out:
        out["stable"] = np.int8(out["stable"])
        if not out["stable"] and speak:
            warn(f"{label}: not a stable minimum after {st.info['escapes']} escape(s) and "
                  f"{st.info.get('cycles', 0)} compression cycle(s) from its saddle "
                  f"({st.info['negative_curvatures']} negative curvature(s) of the full "
                  f"Hessian): written with stable = 0 in /observables")
    return out




def warn(msg):
    """A warning line on stderr (the caller decides which rank speaks)."""
    print(f"parjam: warning: {msg}", file=sys.stderr, flush=True)
