#!/usr/bin/env python3
"""Peak memory of one soft-mode cut (3D, one plane at x = L/2, block null-space method, 1 rank):
main's single-block module (``git show d5de07f:parjam/softmodes.py``, imported from a temporary
directory) against the column-block package ``parjam.softmodes`` (``--columns 64``, and one block
for reference) and the column blocks with the basis out of core (``scratch``: ``--scratch``, a
temporary directory under bench-out/mem), side by side in one run.  Run by hand, never in the
test suite:

    source scripts/mpi-env
    .venv/bin/python scripts/bench_softmodes_memory.py [--sizes 1024 4096 8192]
        [--columns 64] [--variants old "one block" columns scratch] [--tile 8192 1024]
        [--out docs/bench-softmodes-memory.md]

The first variant given is the reference of the ratios and of the agreement check.

Packings: bench-out/mem/nN/member0000_phi_c.h5, made when missing with ``parjam pack --dim 3
--n N --dphi 1e-8 --phic-method extrapolate --members 1 --seed 1`` (analysed with
--allow-hyperstatic: they are 1-2 contacts from isostatic).  Every (N, variant) is a fresh
process, so its peak resident set (getrusage ru_maxrss) is that of one cut alone; the page also
gives the resident set before the analysis (packing read, cut prepared) and checks that the
variants agree (count, extension spectrum, f(x)).  The last section extrapolates to N = 1e5.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PARJAM = os.path.join(ROOT, ".venv", "bin", "parjam")
PYTHON = os.path.join(ROOT, ".venv", "bin", "python")
OLD_COMMIT = "d5de07f"

CHILD = r"""
import json, resource, sys, time
import numpy as np
variant, path, columns, olddir, scratchdir = sys.argv[1:4] + sys.argv[4:6]
columns = int(columns)
from parjam import env; from parjam.files import h5md
PETSc = env.petsc()
comm = PETSc.COMM_WORLD
if variant == "old":
    sys.path.insert(0, olddir)
    import old_softmodes as sm
else:
    from parjam import softmodes as sm
pack = h5md.read_packing(path)
cs = sm.prepare(pack, [sm.Plane(0, 0.5)], allow_hyperstatic=True)
def maxrss():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
before = maxrss()
stages = []  # peak so far when analyze reports the count, then the basis
t0 = time.perf_counter()
if variant == "old":
    res = sm.analyze(comm, cs, 0.1, 10, lambda msg: stages.append(maxrss()))
elif variant == "scratch":
    with sm.scratch_space(comm, scratchdir) as space:
        res = sm.analyze(comm, cs, 0.1, 10, lambda msg: stages.append(maxrss()),
                         columns=columns, scratch=space)
else:
    res = sm.analyze(comm, cs, 0.1, 10, lambda msg: stages.append(maxrss()),
                     columns=None if variant == "one block" else columns)
seconds = time.perf_counter() - t0
peak = maxrss()
print(json.dumps({"before_mb": before, "peak_mb": peak, "seconds": seconds,
                  "count_mb": stages[0], "basis_mb": stages[1],
                  "n_active": int(cs.n), "q": int(cs.q), "count": int(res.count),
                  "n_soft": int(res.n_soft), "e": res.e.tolist(),
                  "f": res.overlap[:, 1].tolist(), "f_nt": res.overlap[:, 2].tolist()}))
"""

VARIANTS = ("old", "one block", "columns", "scratch")
IN_CORE_BASIS = {"old": None, "one block": None, "columns": 1.0, "scratch": 0.0}  # copies held
#   by design (None: the measured ratio of the largest N, rounded)


def packing(n, tile_from=None):
    """The N = n packing; with ``tile_from`` = m (n = 8 m) the m packing tiled 2 x 2 x 2."""
    path = os.path.join(ROOT, "bench-out", "mem", f"n{n}", "member0000_dphi1.0e-08.h5")
    if os.path.exists(path):
        return path, "packed"
    if tile_from:
        return tiled(packing(tile_from)[0], n), f"N = {tile_from} tiled 2 x 2 x 2"
    print(f"making the N = {n} packing ...", flush=True)
    subprocess.run([PARJAM, "pack", "--dim", "3", "--n", str(n), "--dphi", "1e-8",
                    "--phic-method", "extrapolate", "--members", "1", "--seed", "1",
                    "--out", os.path.dirname(path), "-q"], check=True)
    return path, "packed"


def tiled(src, n):
    """A periodic packing repeated twice along every axis (8x the particles; its contact
    network is the tiled one, 7(d - 1) contacts short of isostatic: analysed with
    --allow-hyperstatic, which counts d + q - 1 - (Nc - Nc_iso))."""
    path = os.path.join(ROOT, "bench-out", "mem", f"tiled{n}.h5")
    if os.path.exists(path):
        return path
    code = f"""
import itertools, numpy as np
from parjam import env; from parjam.files import h5md; from parjam.net import network
from parjam.net.system import Packing
p = h5md.read_packing({src!r})
shifts = np.array(list(itertools.product((0, 1), repeat=p.d)), float) * p.L
pos = np.concatenate([p.pos + s for s in shifts])
big = Packing(pos, np.tile(p.diam, len(shifts)), 2 * p.L, p.alpha, p.eps)
assert big.n == {n}
h5md.write_packing({path!r}, big, network.analyze(big), {{}})
"""
    subprocess.run([PYTHON, "-c", code], check=True, cwd=ROOT)
    return path


def old_module(tmp):
    src = subprocess.run(["git", "-C", ROOT, "show", f"{OLD_COMMIT}:parjam/softmodes.py"],
                         check=True, capture_output=True, text=True).stdout
    with open(os.path.join(tmp, "old_softmodes.py"), "w") as fh:
        fh.write(src)
    return tmp


def run(variant, path, columns, olddir, scratchdir):
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    out = subprocess.run([PYTHON, "-c", CHILD, variant, path, str(columns), olddir, scratchdir],
                         capture_output=True, text=True, env=env, cwd=ROOT)
    if out.returncode:
        sys.exit(f"{variant} on {path} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def fit_power(x, y):
    b, a = np.polyfit(np.log(x), np.log(y), 1)
    return np.exp(a), b


def page(rows, columns, sizes, made, variants):
    ref = variants[0]
    lines = [
        "# Benchmark: peak memory of one soft-mode cut, single block against column blocks, "
        "in core and out of core",
        "",
        "Made by `scripts/bench_softmodes_memory.py` (run by hand; see its docstring). 3D "
        "packings (`parjam pack --dim 3 --n N --dphi 1e-8 --phic-method extrapolate --seed 1`), "
        "one plane cut at x = L/2, the whole analysis of `parjam softmodes` (inertia count, null "
        "basis by block inverse iteration, Eq. 3 check, extension, f(x), trial modes, "
        "variational count) on 1 rank, each in a fresh process. `old` is main's module "
        f"(`git show {OLD_COMMIT}:parjam/softmodes.py`), one block of n_soft + 8 columns; "
        f"`one block` is the new package with `columns=None`; `columns` is the new package "
        f"with `--columns {columns}` (the default); `scratch` is `columns` with the basis out of "
        "core (`--scratch`, files on the local disk). Variants run: "
        + ", ".join(f"`{v}`" for v in variants) + f" (ratios against `{ref}`). "
        "`before` is the resident set after reading "
        "the packing and cutting it, `peak` the peak resident set of the process (MB), "
        "`extra` = peak - before. Packings: "
        + "; ".join(f"N = {n}: {made[n]}" for n in sizes) + ".",
        "",
        "| N | N' | q | soft modes | variant | before MB | after count MB | after basis MB | "
        f"peak MB | extra MB | extra / {ref} | seconds | seconds / {ref} | "
        "one basis N'd n_soft 8 B (MB) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for n in sizes:
        old = rows[(n, ref)]
        for v in variants:
            r = rows[(n, v)]
            basis_mb = r["n_active"] * 3 * r["n_soft"] * 8 / 2**20
            extra, extra_old = r["peak_mb"] - r["before_mb"], old["peak_mb"] - old["before_mb"]
            lines.append(f"| {n} | {r['n_active']} | {r['q']} | {r['n_soft']} | {v} | "
                         f"{r['before_mb']:.0f} | {r['count_mb']:.0f} | {r['basis_mb']:.0f} | "
                         f"{r['peak_mb']:.0f} | {extra:.0f} | "
                         f"{extra / extra_old:.2f} | {r['seconds']:.1f} | "
                         f"{r['seconds'] / old['seconds']:.2f} | {basis_mb:.0f} |")
    lines += ["", f"Agreement with `{ref}` (max |difference| over the extension spectrum e and "
              "f(x) with and without the localised modes; counts equal):", ""]
    for n in sizes:
        old = rows[(n, ref)]
        for v in variants[1:]:
            r = rows[(n, v)]
            de = np.abs(np.subtract(r["e"], old["e"])).max()
            df = max(np.abs(np.subtract(r["f"], old["f"])).max(),
                     np.abs(np.subtract(r["f_nt"], old["f_nt"])).max())
            same = "equal" if r["count"] == old["count"] else "DIFFERENT"
            lines.append(f"- N = {n}, {v}: count {same} ({r['count']}), |de| {de:.1e}, "
                         f"|df| {df:.1e}")
    lines += ["", "## Extrapolation to N = 1e5 (one cut, 1 rank)", "",
              "Each variant's extra memory is split into the MUMPS factors (`after count` - "
              "`before`: the inertia factorisations, the same size as the factor of M + tau k I "
              "that the basis keeps and of the uncut M in the variational count), the basis "
              "copies (N' d n_soft 8 B each) and the rest; each part is fitted as a power of N "
              "over the sizes measured and summed at N = 1e5.", ""]
    ns = np.array(sizes, float)
    q = np.array([rows[(n, ref)]["n_soft"] for n in sizes], float)
    aq, bq = fit_power(ns, q)
    q5 = aq * 1e5**bq
    basis5 = 1e5 * 3 * q5 * 8 / 2**30
    lines.append(f"- Soft modes per cut: n_soft = {aq:.3g} N^{bq:.2f} (fit), {q5:.0f} at "
                 f"N = 1e5 (one basis copy N d n_soft 8 B = {basis5:.1f} GB).")
    factor = np.array([rows[(n, ref)]["count_mb"] - rows[(n, ref)]["before_mb"]
                       for n in sizes])
    af, bf = fit_power(ns, factor)
    factor5 = af * 1e5**bf / 1024
    lines.append(f"- MUMPS factor (count stage): {af:.3g} N^{bf:.2f} MB -> {factor5:.1f} GB at "
                 "N = 1e5 (docs/scaling.md's fill fit, 6.48 dof^1.46 entries, gives 5.1 GB).")
    for v in variants:
        basis = np.array([rows[(n, v)]["n_active"] * 3 * rows[(n, v)]["n_soft"] * 8 / 2**20
                          for n in sizes])
        extra = np.array([rows[(n, v)]["peak_mb"] - rows[(n, v)]["before_mb"] for n in sizes])
        copies = (extra - factor) / basis
        # the single block holds a fixed number of n x n_soft arrays at once (its measured
        # ratio); the column blocks hold one basis by design, the rest is fitted
        c = float(np.round(copies[-1])) if IN_CORE_BASIS[v] is None else IN_CORE_BASIS[v]
        rest = np.maximum(extra - factor - c * basis, 1.0)
        ar, br = fit_power(ns, rest)
        total5 = 0.1 + factor5 + c * basis5 + ar * 1e5**br / 1024
        lines.append(f"- {v}: (extra - factor) / basis = "
                     + ", ".join(f"{x:.1f}" for x in copies)
                     + f" at N = {', '.join(map(str, sizes))}; {c:.0f} basis cop"
                     f"{'y' if c == 1 else 'ies'} in memory + factor + the rest ({ar:.3g} N^{br:.2f} MB) "
                     f"+ 0.1 GB before: {total5:.1f} GB at N = 1e5 "
                     f"({'fits' if total5 < 16 else 'does not fit'} in 16 GB); with the factor "
                     f"of docs/scaling.md's fill fit (5.1 GB) "
                     f"{total5 - factor5 + 5.1:.1f} GB.")
    return lines


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[1024, 4096, 8192])
    p.add_argument("--columns", type=int, default=64)
    p.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    p.add_argument("--tile", type=int, nargs=2, action="append", default=[], metavar=("N", "M"),
                   help="make N by tiling the M packing 2 x 2 x 2 when N has no packing yet")
    p.add_argument("--out", default=os.path.join(ROOT, "docs", "bench-softmodes-memory.md"))
    p.add_argument("--json", default=os.path.join(ROOT, "bench-out", "mem", "results.json"))
    args = p.parse_args()
    rows, made = {}, {}
    scratch = os.path.join(ROOT, "bench-out", "mem")  # the local disk, not a tmpfs
    os.makedirs(scratch, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="parjam-oldsoft-") as tmp:
        olddir = old_module(tmp)
        tiles = dict(args.tile)
        for n in args.sizes:
            path, made[n] = packing(n, tiles.get(n))
            for v in args.variants:
                t0 = time.time()
                rows[(n, v)] = run(v, path, args.columns, olddir, scratch)
                r = rows[(n, v)]
                print(f"N = {n} {v}: peak {r['peak_mb']:.0f} MB (before {r['before_mb']:.0f}), "
                      f"{r['n_soft']} modes, {time.time() - t0:.0f} s", flush=True)
    os.makedirs(os.path.dirname(args.json), exist_ok=True)
    with open(args.json, "w") as fh:
        json.dump({f"{n}|{v}": r for (n, v), r in rows.items()}, fh)
    lines = page(rows, args.columns, args.sizes, made, args.variants)
    with open(args.out, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
