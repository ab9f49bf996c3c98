"""Making the states of one ensemble member and writing them: the work behind ``parjam pack``."""

import os
import sys
import time

import h5py
import numpy as np

from parjam import faults
from parjam.progress import member as member_name
from parjam.files import h5md, manifest, outputs
from parjam.net import order
from parjam.pack import checkpoint, filestart, statefile
from parjam.net.network import analyze
from parjam.errors import UnjammedError
from parjam.pack.packing import RESOLVED_FRACTION, JamSettings, Jammer, LadderUnjammed
from parjam.pack.randomstart import member_rng, start_rows
from parjam.net.system import Packing


def settings_from(args):
    lo, hi = args.energy_window
    return JamSettings(ftol=args.ftol, e_low=lo, e_high=hi)


def member_states(args, member, comm, progress, checkpoint=None):
    """Every requested state of one member, in the order they are computed."""
    rng = member_rng(args.seed, member)
    start_phi = args.phi if args.phi is not None else args.phi_start
    if getattr(args, "start", None):  # pack --from FILE: this rank's block rows of the file
        start = filestart.start_rows(comm, args.start, args.alpha, args.phi_start)
    else:  # this rank's block rows of the random start: no rank makes all N particles
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
            resolution_flags(states, resolution, f"{member_name(member)} ")
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


def resolution_flags(states, resolution, label_prefix):
    """Record the resolution of phi_c in every state and flag (file and one line on stderr)
    each requested dphi that it does not resolve to RESOLVED_FRACTION."""
    for st in states:
        st.info["phi_c_resolution"] = resolution
        dphi = st.info.get("dphi")
        if dphi is None or st.label == "phi_c":
            continue
        ok = resolution <= RESOLVED_FRACTION * dphi
        st.info["dphi_resolved"] = int(ok)
        if not ok:
            _warn(f"{label_prefix}{st.label}: dphi = {dphi:.1e} is below what phi_c resolves "
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
    """The contact network of a State: on the slabs from its rows (parjam.pack.statefile, collective),
    serially (network.analyze) for a State made from a whole Packing."""
    if isinstance(st.rows, Packing):
        return analyze(st.rows)
    return st.rows.network()


def state_hexatic(st, net):
    """(local, global) hexatic order of a State (parjam.net.order), from its rows where it has
    them (collective)."""
    if isinstance(st.rows, Packing):
        return order.hexatic_order(st.rows)
    return statefile.hexatic_order(st.rows, net)


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
        _warn(f"{label}: {warning}")
    rel = net.summary()["max_force_rel"]
    if rel > REL_FORCE_WARN and speak:
        _warn(f"{label}: force balance only {rel:.1e} of the mean contact force "
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
            _warn(f"{label}: its own contact network puts it at dphi = "
                  f"{st.info['dphi_virial']:.2e} from jamming (virial relation), not "
                  f"phi - phi_c = {label_dphi:.2e} (tolerance "
                  f"{virial_tolerance(label_dphi):.1%}): it re-jammed at another phi_c on the "
                  f"way (dphi_virial_ok = 0 in /observables)")
    if "stable" in out:
        out["stable"] = np.int8(out["stable"])
        if not out["stable"] and speak:
            _warn(f"{label}: not a stable minimum after {st.info['escapes']} escape(s) and "
                  f"{st.info.get('cycles', 0)} compression cycle(s) from its saddle "
                  f"({st.info['negative_curvatures']} negative curvature(s) of the full "
                  f"Hessian): written with stable = 0 in /observables")
    return out


def _warn(msg):
    print(f"parjam: warning: {msg}", file=sys.stderr, flush=True)


def file_name(out, member, state):
    return os.path.join(out, f"member{member:04d}_{state.label}.h5")


def member_checkpoint(args, member, comm, progress, run_params):
    """The member's checkpoint (parjam.pack.checkpoint) in DIR/.checkpoint, or None when
    --checkpoint-every is 0; with --no-resume an old one is discarded."""
    every = getattr(args, "checkpoint_every", 0.0)
    if run_params is None or every <= 0:
        return None
    path = checkpoint.path_for(args.out, member)
    if not args.resume and comm.getRank() == 0 and os.path.exists(path):
        os.remove(path)
    ck = checkpoint.Checkpoint(path, comm, every, {"member": member, **run_params}, progress)
    if ck.loaded:
        progress(f"resuming from {path}: {len(ck.done)} minimisations finished"
                 + (", one in progress" if ck.pending is not None else ""))
    return ck


class MemberIncomplete(UnjammedError):
    """A member's ladder (or target pressures) unjammed at one step: the jammed states before
    it are written; ``rows`` are their summary rows (group rank 0)."""

    def __init__(self, message, rows):
        super().__init__(message, collective=False)
        self.rows = rows


def pack_member(args, member, comm, progress, run_params=None):
    """Compute, write (by row blocks) and summarise the states of one ensemble member; then its
    manifest record (parjam.files.manifest), so that a restarted run skips it.  ``args`` is the
    member's parjam.pack.protocol.PackingProtocol (from ``parjam pack`` or a scene).  Where a step
    of its ladder unjams, the jammed states before it are written and MemberIncomplete (an
    UnjammedError) is raised after them, without the manifest record."""
    t0 = time.time()
    ck = member_checkpoint(args, member, comm, progress, run_params)
    states, protocol, totals, stopped = member_states(args, member, comm, progress, ck)
    rows = []
    paths = []
    root = comm.getRank() == 0
    for st in states:
        net = state_network(st)  # on the slabs, from the state's rows (collective)
        hexatic = state_hexatic(st, net)
        params = {
            "protocol": protocol, "ladder": args.ladder if "ladder" in protocol else "none",
            "seed": args.seed, "member": member, "dimension": args.dim, "n": args.n,
            "dispersity": args.dispersity, "ratio": args.ratio, "ftol": args.ftol,
            "energy_window": list(args.energy_window), "state": st.label,
            "minimiser_status": st.result.status, "group_ranks": comm.getSize(),
            "seconds": time.time() - t0,
            **{k: v for k, v in st.info.items()}, **totals,
        }
        path = file_name(args.out, member, st)
        prov = h5md.provenance(comm.tompi4py().Get_size(), {"world_ranks": _world_size()})
        extra = quality_checks(st.rows, net, f"{member_name(member)} {st.label}",
                               st.phi - st.info.get("phi_c", np.nan), hexatic, speak=root)
        extra.update(stability_observables(st, f"{member_name(member)} {st.label}",
                                           speak=root))
        # by row blocks (parjam.files.rowio, collective): no rank holds all N; a failed write (a full
        # disk) ends every rank of the group with the same line, not an MPI abort
        statefile.write(path, st.rows, net, params, prov, extra)
        if root:  # one row per state, however many ranks share the member
            paths.append(path)
            rows.append({"member": member, "state": st.label, "file": path, **net.summary(),
                         "phi_c": st.info.get("phi_c", np.nan),
                         "stable": int(st.info.get("stable", 1)),
                         "dphi_virial_ok": int(st.info.get("dphi_virial_ok", 1))})
    if stopped is not None:
        # the jammed states are written, but the member is not finished: no manifest record
        # (a rerun recomputes it, from its checkpoint if any) and an UnjammedError (exit 3)
        raise MemberIncomplete(f"{member_name(member)}: {stopped}; its {len(states)} jammed "
                               f"state(s) before that step are written "
                               f"(ladder_unjammed_at = {stopped.step:.1e} in /observables)",
                               rows)
    if run_params is not None:
        outputs.on_root(comm, lambda: manifest.write_member_record(args.out, member, paths,
                                                                   run_params))
    if ck is not None:
        ck.remove()
    progress(f"done in {time.time() - t0:.1f} s ({totals['fire_steps']} FIRE steps, "
             f"{totals['newton_steps']} Newton steps)")
    faults.point("pack.member")  # PARJAM_FAULT testing hook (parjam/faults.py)
    return rows


SUMMARY_KEYS = ("phi", "N_active", "excess", "z", "dz", "pressure", "max_force",
                "max_force_rel")


def rows_from_files(out, member, files):
    """Summary rows of a finished member, read back from its files (resumed runs)."""
    rows = []
    for name in sorted(files):
        path = os.path.join(out, name)
        with h5py.File(path, "r") as f:
            row = {key: h5md.observable(f, key) for key in SUMMARY_KEYS}
            for key in ("stable", "dphi_virial_ok"):
                row[key] = int(h5md.observable(f, key)) if key in f["observables"] else 1
            par = f["parameters"].attrs
            state = par["state"]
            row.update(member=member, file=path, phi_c=float(par.get("phi_c", np.nan)),
                       state=state.decode() if isinstance(state, bytes) else str(state))
        rows.append(row)
    return rows


def _world_size():
    from mpi4py import MPI

    return MPI.COMM_WORLD.Get_size()


def print_table(rows, d="d"):
    """The states of every member, one row each (members counted from 1, as every message
    counts them: member 1's files are member0000_*), with a row of units under the header
    (parjam.units: reduced units, d the dimension)."""
    from parjam import units

    rows = sorted(rows, key=lambda r: (r["member"], r["phi"]))
    head = (f"{'member':>6} {'state':>12} {'phi_c':>14} {'phi':>14} {'N_act':>6} {'Nc-iso':>6} "
            f"{'z':>8} {'dz':>10} {'p':>15} {'max|F|':>11} {'|F|rel':>9}")
    print(head)
    print(f"{'':>6} {'':>12} {'':>14} {'':>14} {'':>6} {'':>6} {'':>8} {'':>10} "
          f"{units.text('pressure', d):>15} {units.text('force'):>11} {'':>9}")
    for r in rows:
        print(f"{r['member'] + 1:>6} {r['state']:>12} {r['phi_c']:>14.10f} {r['phi']:>14.10f} "
              f"{r['N_active']:>6} {r['excess']:>6} {r['z']:>8.4f} {r['dz']:>10.3e} "
              f"{r['pressure']:>15.4e} {r['max_force']:>11.2e} {r['max_force_rel']:>9.2e}")
    print(stability_line(rows))
    line = label_line(rows)
    if line:
        print(line)


def stability_line(rows):
    """The ensemble's count of states that are not stable minima (flagged, not dropped)."""
    bad = [(r["member"], r["state"]) for r in rows if not r.get("stable", 1)]
    members = sorted({m for m, _ in bad})
    if not bad:
        return f"stability: all {len(rows)} states are stable minima (Nc >= Nc_iso)"
    return (f"stability: {len(bad)} of {len(rows)} states in {len(members)} member(s) are NOT "
            f"stable minima (flagged stable = 0): " + ", ".join(f"{m + 1} {s}" for m, s in bad))


def label_line(rows):
    """The ensemble's count of states whose own virial dphi is off their label (``virial_flags``),
    or None if there is none."""
    bad = [(r["member"], r["state"]) for r in rows if not r.get("dphi_virial_ok", 1)]
    if not bad:
        return None
    return (f"labels: {len(bad)} state(s) re-jammed at another phi_c on the way (their own "
            f"virial dphi is off their label; dphi_virial_ok = 0): "
            + ", ".join(f"{m + 1} {s}" for m, s in bad))
