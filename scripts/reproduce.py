#!/usr/bin/env python3
"""The paper's figures and laws from the bundled scenes' results (docs/results/reproduction.md).

    mpirun -n 2 parjam run scenes/paper-3d.toml --out results/repro/paper-3d   (and the others)
    python scripts/reproduce.py --results results/repro --img docs/img \
        --json results/repro/fits.json

The same as ``parjam plot results/repro --img docs/img --json results/repro/fits.json``
(parjam.plot.paper), plus the fits printed as JSON.  Whatever scene has not been run is skipped.
"""

import argparse
import json
import os

from parjam.plot import paper


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--results", default="results/repro")
    ap.add_argument("--img", default="docs/img")
    ap.add_argument("--json", default="results/repro/fits.json")
    args = ap.parse_args(argv)
    os.makedirs(args.img, exist_ok=True)
    made, fits = paper.reproduce(args.results, args.img, args.json)
    print(json.dumps(fits, indent=1))
    print("figures:", *made, sep="\n  ")


if __name__ == "__main__":
    main()
