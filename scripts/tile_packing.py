#!/usr/bin/env python3
"""Make a large jammed packing by tiling a small one k x k (x k) times: the copies of a periodic
packing in a box of edge k L are again in force balance, with the same contacts per particle,
rattlers and pressure (a k^d-fold supercell; its vibrational spectrum holds the small one's
modes, which is fine for memory and time measurements, not for physics at long wavelengths).

    .venv/bin/python scripts/tile_packing.py SMALL.h5 K OUT.h5

Writes OUT.h5 in the layout of docs/reference/file-format.md (parjam.files.h5md.write_packing, one rank), with
the /parameters of the small file and ``tiled_from``/``tiles`` added.
"""

import argparse
import itertools
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from parjam.files import h5md
from parjam.errors import ParjamError  # noqa: E402
from parjam.net.network import analyze  # noqa: E402
from parjam.net.system import Packing  # noqa: E402


def tiled(pack, k):
    """The k^d supercell of ``pack`` (particles of copy c shifted by c L, in copy order)."""
    shifts = np.array(list(itertools.product(range(k), repeat=pack.d)), dtype=float) * pack.L
    pos = (pack.pos[None, :, :] + shifts[:, None, :]).reshape(-1, pack.d)
    meta = {key: val for key, val in pack.meta.items() if key != "source"}
    if "species" in meta:
        meta["species"] = np.tile(np.asarray(meta["species"]), len(shifts))
    return Packing(pos, np.tile(pack.diam, len(shifts)), k * pack.L, pack.alpha, pack.eps, meta)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("packing")
    ap.add_argument("k", type=int, help="copies per axis (>= 1)")
    ap.add_argument("out")
    args = ap.parse_args(argv)
    if args.k < 1:
        print(f"tile_packing: k must be >= 1, got {args.k}", file=sys.stderr)
        return 2
    try:
        small = h5md.read_packing(args.packing)
    except ParjamError as exc:
        print(f"tile_packing: {exc}", file=sys.stderr)
        return 2
    big = tiled(small, args.k)
    net = analyze(big)
    params = {key: val for key, val in big.meta.items() if key != "species"}
    params.update(tiled_from=os.path.abspath(args.packing), tiles=args.k)
    h5md.write_packing(args.out, big, net, params)
    print(f"{args.out}: N = {big.n} ({args.k}^{big.d} x {small.n}), L = {big.L:.6g}, "
          f"z = {net.z:.4f}, p = {net.pressure:.4e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
