"""One ensemble member of a packing study, from its start to its files: the work behind
``parjam pack`` and the pack stages of ``parjam run``.  The states come from
parjam.pack.ensemble (physics); here they are written by row blocks (parjam.files.rowio), the
member is recorded in the manifest (parjam.files.manifest) and checkpointed
(parjam.files.checkpoint), and the ensemble's table is printed."""

import os
import time

import h5py
import numpy as np

from parjam import faults
from parjam.errors import UnjammedError
from parjam.progress import member as member_name
from parjam.files import checkpoint, h5md, manifest, outputs, rowio
from parjam.pack import filestart, staterows
from parjam.pack.ensemble import (member_states, quality_checks, stability_observables,
                                  state_hexatic, state_network)


def write_state(path, rows, net, parameters, prov=None, observables=None):
    """A state's packing file (h5md.write_packing's layout and content) from its rows, by row
    blocks (collective): the network's summary and stress, then ``observables``."""
    obs = dict(net.summary(), stress_tensor=net.stress, **(observables or {}))
    rowio.write_packing_rows(rows.comm, path, staterows.packing_rows(rows, net), rows.d,
                             rows.L, rows.alpha, rows.eps, rows.phi, obs, parameters, prov)


def file_name(out, member, state):
    return os.path.join(out, f"member{member:04d}_{state.label}.h5")


def member_checkpoint(args, member, comm, progress, run_params):
    """The member's checkpoint (parjam.files.checkpoint) in DIR/.checkpoint, or None when
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
    """A member's ladder (or target pressures) unjammed at one step, also when made again in
    smaller steps (parjam.pack.packing.Jammer.rejam): the jammed states before it are written;
    ``rows`` are their summary rows (group rank 0), ``step`` the dphi (or pressure) that
    unjammed."""

    def __init__(self, message, rows, member, step, n_states):
        super().__init__(message, collective=False)
        self.rows = rows
        self.member, self.step, self.n_states = member, step, n_states


def pack_member(args, member, comm, progress, run_params=None):
    """Compute, write (by row blocks) and summarise the states of one ensemble member; then its
    manifest record (parjam.files.manifest), so that a restarted run skips it.  ``args`` is the
    member's parjam.pack.protocol.PackingProtocol (from ``parjam pack`` or a scene).  Where a step
    of its ladder unjams, the jammed states before it are written and MemberIncomplete (an
    UnjammedError) is raised after them, without the manifest record."""
    t0 = time.time()
    ck = member_checkpoint(args, member, comm, progress, run_params)
    start = None
    if getattr(args, "start", None):  # pack --from FILE: this rank's block rows of the file
        start = filestart.start_rows(comm, rowio.read_rows(comm, args.start), args.alpha,
                                     args.phi_start)
    states, protocol, totals, stopped = member_states(args, member, comm, progress, ck, start)
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
        write_state(path, st.rows, net, params, prov, extra)
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
                               rows, member, stopped.step, len(states))
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
    (parjam.units: reduced units, d the dimension).  ``dphi`` is phi - phi_c of the state: the
    row of the state named phi_c (the bisection's last jammed state) shows how far above the
    refined phi_c it lies, so that no label contradicts the numbers beside it."""
    from parjam import units

    rows = sorted(rows, key=lambda r: (r["member"], r["phi"]))
    head = (f"{'member':>6} {'state':>12} {'phi_c':>14} {'phi':>14} {'dphi':>9} {'N_act':>6} "
            f"{'Nc-iso':>6} {'z':>8} {'dz':>10} {'p':>15} {'max|F|':>11} {'|F|rel':>9}")
    print(head)
    print(f"{'':>6} {'':>12} {'':>14} {'':>14} {'':>9} {'':>6} {'':>6} {'':>8} {'':>10} "
          f"{units.text('pressure', d):>15} {units.text('force'):>11} {'':>9}")
    for r in rows:
        print(f"{r['member'] + 1:>6} {r['state']:>12} {r['phi_c']:>14.10f} {r['phi']:>14.10f} "
              f"{r['phi'] - r['phi_c']:>9.2e} {r['N_active']:>6} {r['excess']:>6} "
              f"{r['z']:>8.4f} {r['dz']:>10.3e} {r['pressure']:>15.4e} {r['max_force']:>11.2e} "
              f"{r['max_force_rel']:>9.2e}")
    print(stability_line(rows))
    line = label_line(rows)
    if line:
        print(line)


def stopped_line(stopped, members):
    """The run's count of members whose ladder stopped early (``stopped``: (member, step,
    states written) of each), or None: one line, printed after the table."""
    if not stopped:
        return None
    steps = sorted({step for _, step, _ in stopped})
    at = ", ".join(f"{s:.0e}" for s in steps)
    written = sum(n for _, _, n in stopped)
    names = ", ".join(f"{m + 1} ({s:.0e})" for m, s, _ in sorted(stopped))
    return (f"stopped: {len(stopped)} of {members} member(s) stopped at dphi = {at} (unjammed "
            f"even in smaller steps; {written} state(s) written, the later steps not made): "
            f"member {names}")


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
