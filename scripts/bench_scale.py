#!/usr/bin/env python3
"""One large run end to end, stage by stage, with wall time and peak memory (the goal: N = 10^5
in 3D within 30 min and 16 GB on this machine).  Run by hand, never in the test suite:

    source scripts/mpi-env
    .venv/bin/python scripts/bench_scale.py --n 100000 --ranks 2 --out bench-out/scale \
        [--dphi 1e-3] [--k 100] [--moments 256 --probes 16] [--md docs/scale-run.md]

Stages, each a ``parjam`` command launched with ``$PARJAM_MPIRUN -n R`` (what a user runs):

1. ``pack``   random start at --phi-start, phi_c by decompression and virial extrapolation
              (``--phic-method extrapolate``), then the state at phi_c + dphi;
2. ``modes``  the lowest k modes of the full dynamical matrix (SLEPc shift-and-invert, MUMPS);
3. ``dos``    a stochastic D(omega) (kernel polynomial method on distributed MatMult).

``--stages modes,dos --packing FILE`` times the last two stages on an existing packing.
Each stage writes ``-log_view`` to OUT/logview-STAGE.txt.  Peak memory: the largest sum of the
resident set sizes of all processes of the stage (sampled every 0.2 s from /proc), and the
largest single process.  Results: OUT/scale.json and a Markdown table (--md).
"""

import argparse
import glob
import json
import os
import shlex
import subprocess
import sys
import threading
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PARJAM = os.path.join(ROOT, ".venv", "bin", "parjam")


def tree_rss_mb(pid):
    """(sum, max) resident memory in MB of pid and all its descendants."""
    children = {}
    rss = {}
    for stat in glob.glob("/proc/[0-9]*/stat"):
        try:
            with open(stat) as fh:
                fields = fh.read().rsplit(")", 1)[1].split()
            p = int(stat.split("/")[2])
            children.setdefault(int(fields[1]), []).append(p)  # fields[1]: ppid
            rss[p] = int(fields[21]) * os.sysconf("SC_PAGE_SIZE") / 2**20  # fields[21]: rss
        except (OSError, ValueError, IndexError):
            continue
    todo, seen = [pid], []
    while todo:
        p = todo.pop()
        seen.append(p)
        todo += children.get(p, [])
    vals = [rss.get(p, 0.0) for p in seen]
    return sum(vals), max(vals)


def run_stage(name, argv, out, env):
    """Run one stage; returns its record (seconds, peak memory, exit code)."""
    log = open(os.path.join(out, f"{name}.log"), "w")
    print(f"# {name}: {' '.join(map(shlex.quote, argv))}", flush=True)
    t0 = time.time()
    proc = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, env=env,
                            stdin=subprocess.DEVNULL)
    peak = [0.0, 0.0]

    def sample():
        while proc.poll() is None:
            tot, one = tree_rss_mb(proc.pid)
            peak[0], peak[1] = max(peak[0], tot), max(peak[1], one)
            time.sleep(0.2)

    th = threading.Thread(target=sample, daemon=True)
    th.start()
    rc = proc.wait()
    th.join()
    sec = time.time() - t0
    log.close()
    rec = {"stage": name, "seconds": sec, "peak_mb_total": peak[0], "peak_mb_process": peak[1],
           "returncode": rc, "command": " ".join(map(shlex.quote, argv))}
    print(f"# {name}: {sec:.1f} s, peak {peak[0]:.0f} MB total / {peak[1]:.0f} MB per process, "
          f"exit {rc}", flush=True)
    return rec


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=100000)
    ap.add_argument("--dim", type=int, default=3)
    ap.add_argument("--dphi", type=float, default=1e-3)
    ap.add_argument("--phi-start", type=float, default=0.66)
    ap.add_argument("--ftol", type=float, default=1e-13)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--k", type=int, default=100)
    ap.add_argument("--moments", type=int, default=256)
    ap.add_argument("--probes", type=int, default=16)
    ap.add_argument("--ranks", type=int, default=2)
    ap.add_argument("--stages", default="pack,modes,dos")
    ap.add_argument("--packing", help="use this packing for modes/dos (with --stages modes,dos)")
    ap.add_argument("--out", default=os.path.join(ROOT, "bench-out", "scale"))
    ap.add_argument("--md", help="write a Markdown table here")
    args = ap.parse_args()
    out = os.path.abspath(args.out)
    os.makedirs(out, exist_ok=True)
    env = dict(os.environ)
    launch = shlex.split(env.get("PARJAM_MPIRUN", "mpirun")) + ["-n", str(args.ranks)]
    packdir = os.path.join(out, "pack")
    packing = args.packing or os.path.join(packdir, f"member0000_dphi{args.dphi:.1e}.h5")
    stages = {
        "pack": [PARJAM, "pack", "--dim", str(args.dim), "--n", str(args.n), "--dphi",
                 str(args.dphi), "--phic-method", "extrapolate", "--phi-start",
                 str(args.phi_start), "--ftol", str(args.ftol), "--seed", str(args.seed),
                 "--out", packdir],
        "modes": [PARJAM, "modes", packing, "--matrix", "full", "--k", str(args.k), "--method",
                  "sinvert", "--out", os.path.join(out, "modes.h5")],
        "dos": [PARJAM, "dos", packing, "--method", "kpm", "--moments", str(args.moments),
                "--probes", str(args.probes), "--out", os.path.join(out, "dos.h5")],
    }
    records = []
    for name in args.stages.split(","):
        argv = launch + stages[name] + ["-log_view", f":{os.path.join(out, f'logview-{name}.txt')}"]
        rec = run_stage(name, argv, out, env)
        records.append(rec)
        if rec["returncode"] != 0:
            break
    total = sum(r["seconds"] for r in records)
    peak = max(r["peak_mb_total"] for r in records)
    summary = {"n": args.n, "dim": args.dim, "dphi": args.dphi, "ranks": args.ranks,
               "stages": records, "total_seconds": total, "peak_mb_total": peak}
    with open(os.path.join(out, "scale.json"), "w") as fh:
        json.dump(summary, fh, indent=1)
    lines = ["| stage | ranks | time (s) | peak memory, all processes (MB) | largest process (MB) "
             "| exit |", "|---|---|---|---|---|---|"]
    for r in records:
        lines.append(f"| {r['stage']} | {args.ranks} | {r['seconds']:.0f} | "
                     f"{r['peak_mb_total']:.0f} | {r['peak_mb_process']:.0f} | {r['returncode']} |")
    lines.append(f"| **total** | {args.ranks} | **{total:.0f}** | {peak:.0f} (max) | | |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.md:
        with open(args.md, "w") as fh:
            fh.write(text)
    return 0 if all(r["returncode"] == 0 for r in records) else 1


if __name__ == "__main__":
    sys.exit(main())
