"""Making the states of one ensemble member and writing them: the work behind ``parjam pack``."""

import os
import time

import numpy as np

from parjam import io
from parjam.network import analyze
from parjam.packing import JamSettings, Jammer, member_rng, random_packing


def settings_from(args):
    lo, hi = args.energy_window
    return JamSettings(ftol=args.ftol, e_low=lo, e_high=hi)


def member_states(args, member, comm, progress, checkpoint=None):
    """Every requested state of one member, in the order they are computed."""
    rng = member_rng(args.seed, member)
    start_phi = args.phi if args.phi is not None else args.phi_start
    if getattr(args, "start", None):  # pack --from FILE
        from parjam.importer import from_file

        pack = from_file(args.start, args.alpha)
    else:
        pack = random_packing(args.dim, args.n, start_phi, args.alpha, args.dispersity,
                              args.ratio, rng)
    jammer = Jammer(comm, pack, settings_from(args), progress, checkpoint)
    try:
        if args.phi is not None:
            states = [jammer.at_phi(args.phi, f"phi{args.phi:.4f}")]
            protocol = "quench"
        else:
            phi_c, states, search = find_phi_c(jammer, args, progress)
            if args.pressure:
                protocol = f"{search}+pressure"
                for p in sorted(args.pressure):
                    states.append(jammer.at_pressure(p, phi_c))
            else:
                protocol = f"{search}+ladder"
                states += jammer.ladder(phi_c, args.dphi, args.ladder)
        totals = {"fire_steps": jammer.total_fire, "newton_steps": jammer.total_newton,
                  "force_evaluations": jammer.ff.n_force_calls}
    finally:
        jammer.destroy()
    return states, protocol, totals


def find_phi_c(jammer, args, progress):
    """(phi_c, [the phi_c state to write, if any], protocol name) by the chosen search."""
    if args.phic_method == "extrapolate":
        if args.pressure:  # p ~ dphi^(alpha-1) with a prefactor of order one
            stop = min(p ** (1.0 / (args.alpha - 1.0)) for p in args.pressure)
        else:
            stop = min(args.dphi)
        st = jammer.find_phi_c_from_above(stop)
        phi_c = st.info["phi_c"]
        progress(f"phi_c = {phi_c:.10f} (extrapolated from dphi = {st.info['dphi_est']:.2e}) "
                 f"after {st.info['iterations']} minimisations")
        return phi_c, [], "virial-extrapolation"
    phic = jammer.find_phi_c()
    phi_c = phic.info["phi_c"]
    progress(f"phi_c = {phi_c:.10f} after {phic.info['iterations']} minimisations")
    return phi_c, ([] if args.no_phic_file else [phic]), "ohern-bisection"


REL_FORCE_WARN = 1e-4  # max|F| / mean contact force above this: force balance is poor
# (harmonic phi_c states end near 1e-5: forces ~1e-8 against ftol = 1e-13; alpha = 3 at
# dphi = 1e-8 reaches 1.8e-3)


def quality_checks(pack, net, label, dphi=None):
    """Observables that flag a state which is not what it seems, each with a warning on stderr:
    a crystallised 2D packing (hexatic order, parjam.order) and a force balance that is poor
    relative to the contact forces (e.g. alpha = 3 at dphi = 1e-8, where forces are ~1e-16 and
    the absolute --ftol means little)."""
    from parjam import order

    extra, warning = order.check(pack, net, dphi)  # hexatic order and contact excess
    if warning:
        _warn(f"{label}: {warning}")
    rel = net.summary()["max_force_rel"]
    if rel > REL_FORCE_WARN:
        _warn(f"{label}: force balance only {rel:.1e} of the mean contact force "
              f"(max|F| = {net.max_force:.1e}): contact forces this small (alpha > 2 near phi_c) "
              f"approach round-off; lower --ftol if max|F| is above ~1e-16")
    return extra


def _warn(msg):
    import sys

    print(f"parjam: warning: {msg}", file=sys.stderr, flush=True)


def file_name(out, member, state):
    return os.path.join(out, f"member{member:04d}_{state.label}.h5")


def member_checkpoint(args, member, comm, progress, run_params):
    """The member's checkpoint (parjam.checkpoint) in DIR/.checkpoint, or None when
    --checkpoint-every is 0; with --no-resume an old one is discarded."""
    from parjam import checkpoint

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


def pack_member(args, member, comm, progress, run_params=None):
    """Compute, write (group rank 0) and summarise the states of one ensemble member; then its
    manifest record (parjam.manifest), so that a restarted run skips it.  ``args`` is the
    member's parjam.protocol.PackingProtocol (from ``parjam pack`` or a scene)."""
    from parjam import faults, manifest

    t0 = time.time()
    ck = member_checkpoint(args, member, comm, progress, run_params)
    states, protocol, totals = member_states(args, member, comm, progress, ck)
    rows = []
    paths = []
    for st in states:
        net = analyze(st.pack)
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
        if comm.getRank() == 0:
            prov = io.provenance(comm.tompi4py().Get_size(), {"world_ranks": _world_size()})
            st.pack.meta.setdefault("species", st.pack.meta.get("species"))
            extra = quality_checks(st.pack, net, f"member {member} {st.label}",
                                   st.pack.phi - st.info.get("phi_c", np.nan))
            io.write_packing(path, st.pack, net, params, prov, extra)
            paths.append(path)
        if comm.getRank() == 0:  # one row per state, however many ranks share the member
            rows.append({"member": member, "state": st.label, "file": path, **net.summary(),
                         "phi_c": st.info.get("phi_c", np.nan)})
    if comm.getRank() == 0 and run_params is not None:
        manifest.write_member_record(args.out, member, paths, run_params)
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
    import h5py

    rows = []
    for name in sorted(files):
        path = os.path.join(out, name)
        with h5py.File(path, "r") as f:
            row = {key: io.observable(f, key) for key in SUMMARY_KEYS}
            par = f["parameters"].attrs
            state = par["state"]
            row.update(member=member, file=path, phi_c=float(par.get("phi_c", np.nan)),
                       state=state.decode() if isinstance(state, bytes) else str(state))
        rows.append(row)
    return rows


def _world_size():
    from mpi4py import MPI

    return MPI.COMM_WORLD.Get_size()


def print_table(rows):
    rows = sorted(rows, key=lambda r: (r["member"], r["phi"]))
    head = (f"{'member':>6} {'state':>12} {'phi_c':>14} {'phi':>14} {'N_act':>6} {'Nc-iso':>6} "
            f"{'z':>8} {'dz':>10} {'p':>11} {'max|F|':>9} {'|F|rel':>9}")
    print(head)
    for r in rows:
        print(f"{r['member']:>6} {r['state']:>12} {r['phi_c']:>14.10f} {r['phi']:>14.10f} "
              f"{r['N_active']:>6} {r['excess']:>6} {r['z']:>8.4f} {r['dz']:>10.3e} "
              f"{r['pressure']:>11.4e} {r['max_force']:>9.2e} {r['max_force_rel']:>9.2e}")
