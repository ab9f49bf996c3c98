"""Making jammed packings: ``parjam pack`` on 1 and 2 ranks, per variant of its arguments (the
whole protocol, a quench at fixed phi, ...), timed by PETSc's log.

Limit: the compiled pair kernel (``parjam: force kernel``: the fused FIRE step and the force
evaluations); a protocol cannot be faster than its kernel calls, so the kernel's share of the
compute time says how far from it the rest (neighbour lists, reductions, Newton) keeps it.
Peer: a plain numpy FIRE step (scipy k-d tree rebuilt every step) at the same N, and its lower
bound for the same protocol (its cost per step times parjam's FIRE steps: it has no Newton
steps, so it would need more).  Check: the pressure of every state, recomputed by the numpy
peer from the file's positions.
"""

import glob
import os

import h5py
import numpy as np

from benchmarks import harness, reference

TITLE = "parjam pack (protocol, quench) against its pair kernel and a numpy FIRE"
QUICK = {"n": [64], "ranks": [1], "variant": ["protocol: --dphi 1e-2 --phic-method extrapolate"],
         "peer_steps": 5}


def add_arguments(ap):
    ap.add_argument("--n", type=int, nargs="+", default=[4096])
    ap.add_argument("--dim", type=int, default=3)
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--variant", nargs="+", default=[
        "protocol: --dphi 1e-3 --phic-method extrapolate", "quench: --phi 0.66 --ftol 1e-12"],
        help="LABEL: pack arguments (one member, 3D monodisperse harmonic by default)")
    ap.add_argument("--peer-steps", type=int, default=20,
                    help="numpy FIRE steps timed (0: no peer)")
    ap.add_argument("--timeout", type=float, default=7200)


def state(out):
    """(parameters, pressure, max force) of the last state a member wrote, and the pressure the
    numpy peer finds from its positions."""
    path = sorted(f for f in glob.glob(os.path.join(out, "member0000_*.h5"))
                  if "phi_c" not in f)[-1]
    with h5py.File(path, "r") as f:
        params = dict(f["parameters"].attrs)
        p = float(f["observables/pressure/value"][0])
        fmax = float(f["observables/max_force/value"][0])
    return params, p, fmax, reference.Network.read(path).pressure()


def run(args, trees, work):
    rows = []
    for n in args.n:
        peer = None
        if args.peer_steps:
            rng = np.random.default_rng(args.seed)
            L = (n * np.pi / 6.0 / 0.66) ** (1.0 / 3.0) if args.dim == 3 else \
                (n * np.pi / 4.0 / 0.86) ** 0.5
            peer = reference.fire_step_seconds(rng.uniform(0, L, (n, args.dim)), np.ones(n),
                                               L, args.peer_steps)
        for label, extra in harness.variants(args.variant):
            for tree_label, tree in trees:
                for ranks in args.ranks:
                    out = os.path.join(work, f"{label}-{tree_label}-{n}-{ranks}")
                    log = out + ".log"
                    res = harness.run(["parjam", "pack", "--dim", args.dim, "--n", n, "--seed",
                                       args.seed, "--out", out, "--checkpoint-every", "0", "-q",
                                       *extra, "-log_view", ":" + log], ranks, tree,
                                      args.timeout)
                    row = {"variant": label, "tree": tree_label, "n": n, "ranks": ranks,
                           **res.measured(), "peer_step_s": peer}
                    if not res.ok:
                        rows.append(dict(row, error=res.error))
                        continue
                    params, p, fmax, p_peer = state(out)
                    stages, events = harness.log_view(log)
                    compute = sum(s for name, s in stages.items()  # stage times are exclusive
                                  if name not in ("Main Stage", "Unknown"))
                    calls, kernel = events.get("parjam: force kernel", (0, 0.0))
                    steps = int(params["fire_steps"])
                    rows.append(dict(row, fire_steps=steps,
                                     newton_steps=int(params["newton_steps"]),
                                     evaluations=int(params["force_evaluations"]),
                                     kernel_calls=calls, kernel_s=kernel, compute_s=compute,
                                     rebuilds=events.get("parjam: nbr rebuild", (0, 0))[0],
                                     max_force=fmax, p_diff=abs(p_peer / p - 1)))
    return rows


def per_step(row):
    """Compute seconds per particle per FIRE step (Newton included), ns."""
    return 1e9 * row["compute_s"] / row["fire_steps"] / row["n"] if row.get("fire_steps") else None


def peer_bound(row):
    """The numpy peer's lower bound for the same run over parjam's compute time."""
    if not row.get("fire_steps") or not row.get("peer_step_s"):
        return None
    return row["peer_step_s"] * row["fire_steps"] / row["compute_s"]


COLUMNS = [
    ("variant", "variant", ""), ("tree", "tree", ""), ("N", "n", "d"), ("ranks", "ranks", "d"),
    ("wall s", "seconds", ".1f"), ("compute s", "compute_s", ".1f"),
    ("FIRE steps", "fire_steps", "d"), ("Newton steps", "newton_steps", "d"),
    ("kernel calls", "kernel_calls", "d"), ("kernel s", "kernel_s", ".2f"),
    ("kernel share", lambda r: r["kernel_s"] / r["compute_s"] if r.get("compute_s") else None,
     ".2f"),
    ("ns/particle/step", per_step, ".0f"),
    ("kernel ns/particle/step", lambda r: 1e9 * r["kernel_s"] / r["fire_steps"] / r["n"]
     if r.get("fire_steps") else None, ".0f"),
    ("numpy FIRE ns/particle/step", lambda r: 1e9 * r["peer_step_s"] / r["n"]
     if r.get("peer_step_s") else None, ".0f"),
    ("numpy bound / parjam", peer_bound, ".1f"),
    ("peak MB/rank", "peak_mb", ".0f"), ("max abs F", "max_force", ".1e"),
    ("p vs numpy", "p_diff", ".0e"), ("error", "error", "")]


def notes(rows):
    return ["compute s: the command's stages in `-log_view` (phi_c search, ladder or quench, "
            "stability check, writing; not the start-up in the main stage); kernel: the "
            "`parjam: force kernel` event (the fused FIRE step, two calls per step on several "
            "ranks, and the force evaluations), largest rank; ns/particle/step: compute s / "
            "FIRE steps / N (Newton included), and the same for the kernel; numpy bound: the "
            "numpy FIRE's seconds per step times parjam's FIRE steps (a lower bound: it has no "
            "Newton steps); p vs numpy: relative "
            "difference of the file's pressure and the numpy peer's from the same positions."]
