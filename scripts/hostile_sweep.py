#!/usr/bin/env python3
"""Run the hostile cases of parjam.testing.hostile and print one line per case and the tally.

    scripts/hostile_sweep.py                     # this checkout
    scripts/hostile_sweep.py --pythonpath DIR    # another parjam checkout (e.g. before a fix)
    scripts/hostile_sweep.py --only "FIFO"       # the cases whose name contains FIFO

Each case runs in its own temporary directory; a case still running after 40 s is a hang.
The disk-full cases need a tmpfs mount (root) and are skipped otherwise.
"""

import argparse
import os
import sys
import tempfile

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from parjam.testing.hostile import CASES, run_case  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pythonpath", help="run the parjam found here (PYTHONPATH) instead")
    ap.add_argument("--only", default="", help="cases whose name contains this text")
    args = ap.parse_args()
    tally = {}
    for case in CASES:
        if args.only not in case.name:
            continue
        with tempfile.TemporaryDirectory(prefix="parjam-hostile-") as work:
            out = run_case(case, work, python_path=args.pythonpath)
        kind = out.verdict.split(":")[0]
        tally[kind] = tally.get(kind, 0) + 1
        tags = ",".join(t for t in (case.owner if case.owner != "hostile" else "",
                                    "new" if case.new else "") if t)
        print(f"{out.verdict[:60]:<60} {out.seconds:6.1f} s  [{case.group}{',' + tags if tags else ''}] "
              f"{case.name}", flush=True)
    print("tally: " + ", ".join(f"{k} {v}" for k, v in sorted(tally.items())))


if __name__ == "__main__":
    main()
