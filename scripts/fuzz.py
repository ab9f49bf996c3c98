#!/usr/bin/env python3
"""The long fuzzing profile: the fuzz tests of tests/hostile with many examples per property.

    scripts/fuzz.py                    # 2000 examples per property (weights as in the tests)
    scripts/fuzz.py --examples 20000   # more
    scripts/fuzz.py --mpi              # also under mpirun -n 2 (every rank runs every example)

The CI runs the same tests with 40 per property (tests/hostile/fuzzing.py): a few hundred
examples in all, well under a minute.  This prints hypothesis' statistics per property (examples
tried, failing, invalid) and exits non-zero if any property failed; a failing example is then
shown in full, to be kept as an @example regression in its test.
"""

import argparse
import os
import re
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FILES = ["tests/hostile/test_fuzz.py", "tests/hostile/test_fuzz_importers.py"]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--examples", type=int, default=2000, help="examples per property (2000)")
    ap.add_argument("--mpi", action="store_true", help="then under mpirun -n 2 as well")
    args = ap.parse_args()
    python = os.path.join(ROOT, ".venv", "bin", "python")
    python = python if os.path.exists(python) else sys.executable
    env = dict(os.environ, PARJAM_FUZZ_EXAMPLES=str(args.examples), PYTHONDONTWRITEBYTECODE="1")
    runs = [[python, "-m", "pytest", "-q", "-p", "no:cacheprovider",
             "--hypothesis-show-statistics", *FILES]]
    if args.mpi:
        mpirun = os.environ.get("PARJAM_MPIRUN", "mpirun --oversubscribe").split()
        env.update(OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
                   OMPI_MCA_rmaps_base_oversubscribe="1")
        runs.append(mpirun + ["-n", "2", python, "-m", "parjam.testing.mpi_pytest", "-q", "-p",
                              "no:cacheprovider", *FILES])
    worst = 0
    for cmd in runs:
        r = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
        tried = failing = 0
        for m in re.finditer(r"- (\d+) passing examples, (\d+) failing examples", r.stdout):
            tried += int(m.group(1)) + int(m.group(2))
            failing += int(m.group(2))
        print(r.stdout if r.returncode else r.stdout[-4000:])
        print(f"fuzz: {' '.join(cmd[:3])}...: {tried} examples tried, {failing} failing, "
              f"status {r.returncode}", flush=True)
        worst = max(worst, r.returncode)
    return worst


if __name__ == "__main__":
    sys.exit(main())
