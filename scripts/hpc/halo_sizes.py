#!/usr/bin/env python3
"""Halo of the force evaluation: how many non-owned particles a rank fetches per evaluation
(the halo a ForceField builds for its Verlet list) when N particles are split over P ranks, for the scaling model of
docs/explanation/scaling.md.  No MPI needed: the ranks' contiguous blocks of the cell-ordered numbering
(parjam.pack.randomstart.spatial_order, hessian.row_range) are formed here, on uniform random positions
at phi (the halo is geometry: the jammed structure changes it little).

    .venv/bin/python scripts/hpc/halo_sizes.py --n 100000 1000000 --ranks 2 8 64 256 1024
"""

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

import numpy as np  # noqa: E402


def halo_sizes(pack, ranks, skin_frac=0.2, sample=4):
    """{P: largest halo over ``sample`` ranks spread over the P blocks}."""
    from parjam.net.system import neighbour_pairs

    cut = pack.diam.max() + skin_frac * pack.diam.min()  # ForceField's Verlet cutoff
    pairs = neighbour_pairs(pack.pos, pack.L, cut)
    i, j = pairs[:, 0], pairs[:, 1]
    out = {}
    for p in ranks:
        bounds = np.linspace(0, pack.n, p + 1).astype(np.int64)
        worst = 0
        for r in sorted({int(x) for x in np.linspace(0, p - 1, sample)}):
            lo, hi = bounds[r], bounds[r + 1]
            mine = ((i >= lo) & (i < hi)) | ((j >= lo) & (j < hi))
            need = np.union1d(i[mine], j[mine])
            worst = max(worst, len(need) - np.count_nonzero((need >= lo) & (need < hi)))
        out[p] = worst
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="*", default=[100000, 1000000])
    ap.add_argument("--ranks", type=int, nargs="*", default=[2, 8, 64, 256, 1024])
    ap.add_argument("--phi", type=float, default=0.64)
    a = ap.parse_args()
    from parjam.pack.packing import random_packing

    print("| N | ranks | owned per rank | halo (largest) | halo / N | halo / owned |")
    print("|---|---|---|---|---|---|")
    for n in a.n:
        pack = random_packing(3, n, a.phi, rng=np.random.default_rng(1))
        for p, h in halo_sizes(pack, a.ranks).items():
            print(f"| {n:.0e} | {p} | {n // p} | {h} | {h / n:.4f} | {h / (n / p):.2f} |",
                  flush=True)


if __name__ == "__main__":
    main()
