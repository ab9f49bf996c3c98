#!/usr/bin/env python3
"""How often a ladder step unjams, is made again and recovered, or stops its member: runs
``parjam pack`` on an ensemble and tallies each member's outcome from its files and the
manifest (a recovered state carries ``rejammed = 1`` in /parameters; a stopped member is in the
manifest's ``stopped``), and the stability check's verdicts on the states (``stable`` and
``escapes`` in /parameters).

    python scripts/ladder_census.py --dim 3 --n 256 --members 50 --ranks 2 --out census-3d-256
    python scripts/ladder_census.py --dim 2 --n 256 --dispersity bi --members 50 --out census-2d

Prints one line and writes OUT/census.json.  The ladder is the README's (1e-8 .. 1e-1) unless
--dphi is given; --seed picks the ensemble."""

import argparse
import glob
import json
import os
import shlex
import subprocess
import sys
import time

import h5py


def outcome(out, members):
    """(clean, recovered, stopped) member lists from a finished run's directory, and the
    stability check's verdicts on its states: how many states, how many certified stable,
    and how many saddles the check found and escaped on the way (each state's /parameters)."""
    with open(os.path.join(out, "manifest.json")) as fh:
        man = json.load(fh)
    stopped = sorted(int(m) for m in man.get("stopped", {}))
    recovered = set()
    verdicts = {"states": 0, "stable": 0, "escapes": 0}
    for path in glob.glob(os.path.join(out, "member*_*.h5")):
        with h5py.File(path, "r") as f:
            attrs = f["parameters"].attrs
            if int(attrs.get("rejammed", 0)):
                recovered.add(int(os.path.basename(path)[6:10]))
            verdicts["states"] += 1
            verdicts["stable"] += int(attrs.get("stable", 0))
            verdicts["escapes"] += int(attrs.get("escapes", 0))
    recovered = sorted(recovered - set(stopped))
    clean = [m for m in range(members) if m not in recovered and m not in stopped]
    return clean, recovered, stopped, verdicts


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dim", type=int, default=3)
    p.add_argument("--n", type=int, default=256)
    p.add_argument("--dispersity", default="mono")
    p.add_argument("--members", type=int, default=50)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--dphi", nargs="+", default=["1e-8", "1e-6", "1e-4", "1e-2", "1e-1"])
    p.add_argument("--ranks", type=int, default=1)
    p.add_argument("--out", required=True)
    args = p.parse_args()
    cmd = [sys.executable, "-m", "parjam", "pack", "--dim", str(args.dim), "--n", str(args.n),
           "--dispersity", args.dispersity, "--members", str(args.members), "--seed",
           str(args.seed), "--dphi", *args.dphi, "--out", args.out, "-q"]
    if args.ranks > 1:
        cmd = shlex.split(os.environ.get("PARJAM_MPIRUN", "mpirun --oversubscribe")) + \
            ["-n", str(args.ranks)] + cmd
    t0 = time.time()
    run = subprocess.run(cmd, capture_output=True, text=True)
    seconds = time.time() - t0
    if run.returncode not in (0, 3):
        sys.exit(f"ladder_census: parjam pack failed ({run.returncode}): {run.stderr[-2000:]}")
    clean, recovered, stopped, verdicts = outcome(args.out, args.members)
    result = {"command": " ".join(cmd[cmd.index("pack") - 2:]), "dim": args.dim, "n": args.n,
              "dispersity": args.dispersity, "members": args.members, "seed": args.seed,
              "dphi": args.dphi, "ranks": args.ranks, "seconds": round(seconds, 1),
              "clean": clean, "recovered": recovered, "stopped": stopped, **verdicts}
    with open(os.path.join(args.out, "census.json"), "w") as fh:
        json.dump(result, fh, indent=1)
    print(f"{args.dim}D {args.dispersity} N = {args.n}: {len(clean)} clean, {len(recovered)} "
          f"recovered, {len(stopped)} stopped of {args.members} members ({seconds:.0f} s); "
          f"{verdicts['stable']} of {verdicts['states']} states certified stable, "
          f"{verdicts['escapes']} saddle(s) escaped")


if __name__ == "__main__":
    main()
