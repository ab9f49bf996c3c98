"""Weak scaling of the peak memory per rank: a parjam command at a fixed number of particles per
rank on P = 1, 2, 4, ... ranks (oversubscribed ranks are fine: memory is the point), per
variant of its options, and with ``--old REV`` the code of another commit beside this one on
the same inputs.

Limit: the floor, a process that only starts parjam, PETSc and MPI on P ranks; ideal weak
scaling keeps the rest (peak - floor) flat in P, and ``vs P=1`` shows how far it grows.
Inputs: small jammed packings tiled K^d times (tile_packing.py), the small one and K chosen per
P to come nearest the particles per rank asked for (``pack`` makes its own).  Check: with
``--old``, the old and new outputs compared dataset by dataset (h5_same.py).
"""

import glob
import os

from benchmarks import harness

TITLE = "peak memory per rank of a command at fixed N/P, old tree against new"
QUICK = {"command": ["kpm"], "small": ["tests/data/ref_d3_mono_N128_dphi1e-03.h5"],
         "per_rank": 1000, "ranks": [2]}

PRESETS = {  # name: arguments given (packing, output, N)
    "analyze": lambda f, out, n: ["analyze", "--json", f],
    "kpm": lambda f, out, n: ["dos", "--method", "kpm", f, "--moments", "64", "--probes", "2",
                              "--out", out],
    "moduli": lambda f, out, n: ["moduli", f, "--out", out, "-q"],
    "modes": lambda f, out, n: ["modes", f, "--k", "20", "--method", "sinvert", "--out", out,
                                "-q"],
    "lengths": lambda f, out, n: ["lengths", f, "--what", "lstar", "--out", out, "-q"],
    "softmodes": lambda f, out, n: ["softmodes", f, "--cut", "x=0.5", "--allow-hyperstatic",
                                    "--out", out, "-q"],
    "pack": lambda f, out, n: ["pack", "--dim", "3", "--n", str(n), "--phic-method",
                               "extrapolate", "--dphi", "1e-2", "--seed", "1",
                               "--checkpoint-every", "0", "--out", out, "-q"],
}


def add_arguments(ap):
    ap.add_argument("--command", nargs="+", default=["analyze", "kpm", "moduli"],
                    choices=sorted(PRESETS))
    ap.add_argument("--small", nargs="+", default=[
        "tests/data/ref_d2_bi_N128_dphi1e-03.h5", "tests/data/lengths_d2_N1024_dphi1e-01.h5"],
        help="jammed packings to tile, of one dimension and stable in their box")
    ap.add_argument("--per-rank", type=int, default=25000)
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--variant", nargs="+", default=["default:"],
                    help="LABEL: more arguments of every command (e.g. PETSc options)")
    ap.add_argument("--timeout", type=float, default=7200)


def tiling(smalls, per_rank, ranks):
    """(small packing, K) whose K^d tiling comes nearest per_rank x ranks particles."""
    import h5py

    best = None
    for small in smalls:
        with h5py.File(os.path.join(harness.ROOT, small), "r") as f:
            n, d = f["particles/all/diameter"].shape[0], f["particles/all/box"].attrs["dimension"]
        k = max(1, round((per_rank * ranks / n) ** (1.0 / d)))
        err = abs(n * k ** d / ranks / per_rank - 1)
        if best is None or err < best[0]:
            best = (err, small, k, n * k ** d)
    return best[1:]


def same(a, b):
    """How two runs' outputs compare: 'identical', 'within 1e-8' or the differing names."""
    from h5_same import differences

    if a["text"] is not None:
        return "identical" if a["text"] == b["text"] else "stdout differs"
    files = sorted(glob.glob(os.path.join(a["out"], "*.h5"))) if os.path.isdir(a["out"]) \
        else [a["out"]]
    diffs = []
    for fa in files:
        fb = fa.replace(a["out"], b["out"])
        if not os.path.exists(fb):
            return f"no {os.path.basename(fb)}"
        diffs += differences(fa, fb)[0]
    if not diffs:
        return "identical"
    close = [x for fa in files for x in differences(fa, fa.replace(a["out"], b["out"]), 1e-8)[0]]
    return "within 1e-8" if not close else "differs: " + ", ".join(x.split(":")[0]
                                                                    for x in close[:3])


def run(args, trees, work):
    rows, floor, first = [], {}, {}
    for ranks in args.ranks:
        small, k, n = tiling(args.small, args.per_rank, ranks)
        path = harness.packing(f"{small}:{k}", work)
        for command in args.command:
            n_run = args.per_rank * ranks if command == "pack" else n
            for label, extra in harness.variants(args.variant):
                outs = {}
                for tree_label, tree in trees:
                    if (tree, ranks) not in floor:
                        floor[(tree, ranks)] = harness.floor_mb(ranks, tree)
                    out = os.path.join(work, f"{command}-{label}-{tree_label}-{ranks}")
                    out += "" if command == "pack" else ".h5"
                    res = harness.run(["parjam", *PRESETS[command](path, out, n_run), *extra],
                                      ranks, tree, args.timeout)
                    extra_mb = res.peak - floor[(tree, ranks)]
                    key = (command, label, tree_label)
                    first.setdefault(key, extra_mb)
                    rows.append({"command": command, "variant": label, "tree": tree_label,
                                 "ranks": ranks, "n": n_run, "tiles": f"{small} x {k}^d"
                                 if command != "pack" else "-", "seconds": res.seconds,
                                 "peak_mb": res.peak, "min_mb": min(res.rss_mb, default=None),
                                 "floor_mb": floor[(tree, ranks)], "extra_mb": extra_mb,
                                 "growth": extra_mb / first[key], "rss_mb": res.rss_mb,
                                 "error": None if res.ok else res.error})
                    outs[tree_label] = {"out": out, "text": res.stdout if command == "analyze"
                                        else None, "ok": res.ok}
                if "old" in outs and outs["old"]["ok"] and outs["new"]["ok"]:
                    rows[-1]["same"] = same(outs["old"], outs["new"])
    return rows


COLUMNS = [
    ("command", "command", ""), ("variant", "variant", ""), ("tree", "tree", ""),
    ("P", "ranks", "d"), ("N", "n", "d"), ("N/P", lambda r: r["n"] // r["ranks"], "d"),
    ("packing", "tiles", ""), ("peak MB/rank (max)", "peak_mb", ".0f"),
    ("min", "min_mb", ".0f"), ("floor", "floor_mb", ".0f"),
    ("peak - floor", "extra_mb", ".0f"), ("vs P=1", "growth", ".2f"),
    ("wall s", "seconds", ".1f"), ("old vs new output", "same", ""), ("error", "error", "")]


def notes(rows):
    return ["peak: the largest resident set over the ranks (min: the smallest); floor: the "
            "same for a process that only starts parjam, PETSc and MPI; vs P=1: peak - floor "
            "over the same command's at P = 1 (1 = ideal weak scaling)."]
