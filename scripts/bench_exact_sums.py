#!/usr/bin/env python3
"""What the exact sums cost the fused FIRE step (docs/results/pack-ranks.md), in one tree: the
compiled kernels as they are against a copy whose sums over particles are plain double sums
(the energy summed in pair order, F.v, |F|^2 and |v|^2 accumulated in doubles: what a
rank-dependent kernel would do), and, with ``--old REV``, the kernels of commit REV (its
parjam/pack/_kernels.c from git; the same signature) -- the baseline a change is measured
against.  "exact, energy not asked" is the step as FIRE runs it when no stopping energy is set
(FIRE_FORCES without FIRE_ENERGY: the energy is summed only where progress or the end needs it).  The plain copy is made from parjam/pack/_kernels.c by textual substitution (the script
stops if the source no longer holds the text it replaces); all are compiled with the same flags
and every variant runs the same steps on the same state, interleaved, repeated.  One core, no MPI.

    .venv/bin/python scripts/bench_exact_sums.py --n 16384 65536 --alpha 2 2.5 --old f0a4ae0
"""

import argparse
import ctypes
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from parjam.pack import cellsearch, kernels  # noqa: E402
from parjam.pack.randomstart import random_packing  # noqa: E402

SRC = os.path.join(ROOT, "parjam", "pack", "_kernels.c")

PLAIN = [  # (old, new): the exact accumulators replaced by double sums
    ("forces(npairs, pi, pj, pos, diam, L, d, alpha, eps, lo, hi, f,\n"
     "               (mode & FIRE_ENERGY) ? ae : NULL);",
     "const double e_plain = forces(npairs, pi, pj, pos, diam, L, d, alpha, eps, lo, hi, f,"
     " NULL);"),
    ("                bp[b] = p;\n                bf[b] = fk;\n                bv[b] = vk;\n"
     "                const double ab = fabs(p);\n                pb = ab > pb ? ab : pb;\n",
     "                s_p += p;\n                s_f += fk;\n                s_v += vk;\n"),
    ("            xacc_flush(ap, bp, n, pb, fast, &adds_p);\n"
     "            xacc_flush(af, bf, n, fb, fast, &adds_f);\n"
     "            xacc_flush(av, bv, n, vb, fast, &adds_v);\n", ""),
    ("double fm = 0.0, vm = 0.0, bp[XBLOCK]",
     "double s_p = 0.0, s_f = 0.0, s_v = 0.0, fm = 0.0, vm = 0.0, bp[XBLOCK]"),
    ("acc[FIRE_ACC - 3] = max_bits(fm);",
     "acc[0] = max_bits(e_plain + s_p + s_f + s_v);\n        acc[FIRE_ACC - 3] = max_bits(fm);"),
]


def variant(text, subs):
    for old, new in subs:
        if old not in text:
            raise SystemExit(f"_kernels.c no longer holds {old[:60]!r}: update this script")
        text = text.replace(old, new)
    return text


def compiled(text, folder, name):
    src, so = os.path.join(folder, name + ".c"), os.path.join(folder, name + ".so")
    with open(src, "w") as fh:
        fh.write(text)
    subprocess.run(["cc", *kernels.CFLAGS, "-shared", "-o", so, src, "-lm"], check=True)
    fn = ctypes.CDLL(so).parjam_fire_step
    vp, dbl, i64 = ctypes.c_void_p, ctypes.c_double, ctypes.c_int64
    fn.restype = ctypes.c_int
    fn.argtypes = [ctypes.c_int, i64, i64, ctypes.c_int, vp, vp, vp, vp, dbl, dbl, ctypes.c_int,
                   dbl, dbl, dbl, dbl, i64, vp, vp, vp, vp, dbl, dbl, i64, i64, vp]
    return fn


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="+", default=[16384, 65536])
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--old", metavar="REV", help="also time the kernels of commit REV")
    ap.add_argument("--alpha", type=float, nargs="+", default=[2.0],
                    help="contact laws (2: harmonic, 2.5: Hertz; default 2)")
    args = ap.parse_args()
    text = open(SRC).read()
    texts = {"exact (as built)": text, "plain double sums": variant(text, PLAIN)}
    if args.old:
        texts[f"exact at {args.old}"] = subprocess.run(
            ["git", "-C", ROOT, "show", f"{args.old}:parjam/pack/_kernels.c"], check=True,
            capture_output=True, text=True).stdout
    with tempfile.TemporaryDirectory(prefix="parjam-exact-") as tmp:
        fns = {k: compiled(t, tmp, f"v{i}") for i, (k, t) in enumerate(texts.items())}
        step = kernels.FIRE_UPDATE | kernels.FIRE_FORCES
        modes = {k: step | kernels.FIRE_ENERGY for k in fns}  # older kernels ignore the bit
        fns["exact, energy not asked"] = fns["exact (as built)"]
        modes["exact, energy not asked"] = step
        print(f"load average {os.getloadavg()[0]:.1f}")
        for n, alpha in ((n, a) for n in args.n for a in args.alpha):
            pack = random_packing(3, n, 0.70, alpha, "mono", 1.4, np.random.default_rng(0))
            x0, diam, L = pack.pos.copy(), pack.diam.copy(), pack.L
            pi, pj = cellsearch.cell_pair_lists(np.mod(x0, L), L, diam.max() + 0.2 * diam.min(),
                                                0, n)
            times = {k: [] for k in fns}
            for _ in range(args.repeat):
                for k, fn in fns.items():
                    x, v, f = x0.copy(), np.zeros_like(x0), np.zeros_like(x0)
                    ref, acc = x0.copy(), np.zeros(kernels.FIRE_ACC, dtype=np.int64)

                    def call(mode):
                        return fn(mode, n, n, 3, x.ctypes.data, v.ctypes.data, f.ctypes.data,
                                  ref.ctypes.data, L, 0.01, 0, 0.0, 0.99, 0.001, 0.0, len(pi),
                                  pi.ctypes.data, pj.ctypes.data, x.ctypes.data,
                                  diam.ctypes.data, alpha, 1.0, 0, n, acc.ctypes.data)

                    call(modes[k] & ~kernels.FIRE_UPDATE)
                    t = time.perf_counter()
                    for _ in range(args.steps):
                        call(modes[k])
                    times[k].append((time.perf_counter() - t) / args.steps)
            base = np.median(times["plain double sums"])
            for k, t in times.items():
                print(f"N = {n}, alpha = {alpha:g}: {k:24s} {1e3 * np.median(t):7.3f} ms/step "
                      f"({np.median(t) / base:.3f}x of plain sums)")
        print(f"load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
