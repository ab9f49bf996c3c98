#!/usr/bin/env python3
"""Issue 19's measurements of ``parjam modes`` and the analysis commands, written to
docs/bench-scaling-19.md.  Run by hand, never in the test suite:

    source scripts/mpi-env
    nice -n 10 .venv/bin/python scripts/bench_scaling_19.py --old /tmp/old \
        --weak 1:W1.h5 2:W2.h5 4:W4.h5 8:W8.h5 --strong S3D.h5 --strong-modes S2D.h5

1. **Weak scaling of ``parjam modes --k K``** (MUMPS shift-and-invert) at a fixed number of
   particles per rank: each ``--weak P:FILE`` runs FILE on P ranks, the code of main (``--old``:
   a directory holding main's ``parjam`` package, e.g. ``git archive main | tar -x -C /tmp/old``)
   and of this tree side by side.  Peak RSS per rank from /usr/bin/time (largest and smallest
   over the ranks); the MUMPS factor's own memory from ``-modes_eps_view`` (INFOG(16)/(17): the
   analysis' estimate, most loaded rank / sum; INFOG(18)/(19): allocated at the factorisation;
   INFOG(21)/(22): effectively used), and "rest" = peak RSS - INFOG(18) (the memory that is not
   the factor's; per rank up to the spread between the ranks).  Old and new files are compared
   (scripts/h5_same.py: the per-particle datasets and every value).
2. **Strong scaling 1 -> 2 ranks** of ``analyze``, ``dos --method kpm``, ``moduli`` on
   ``--strong`` and ``modes --k K`` on ``--strong-modes``, from PETSc's ``-log_view``: every
   stage's time and every event above 1 % of the run, the largest time over the ranks.

Every run is one process per rank, oversubscribed on this 2-core machine (memory is what the
weak runs measure; the strong runs' times include the machine's load, reported with them).
"""

import argparse
import os
import re
import shlex
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PY = os.path.join(ROOT, ".venv", "bin", "python")
sys.path.insert(0, os.path.join(ROOT, "scripts"))

from h5_same import differences  # noqa: E402

INFOG = (16, 17, 18, 19, 21, 22)


def mpirun():
    return shlex.split(os.environ.get("PARJAM_MPIRUN", "mpirun --oversubscribe"))


def run(code_dir, ranks, args, log=None):
    """One parjam run on ``ranks`` ranks from ``code_dir``: (peak RSS MB per rank list, seconds,
    exit code, stdout+stderr)."""
    env = dict(os.environ, PYTHONPATH=code_dir, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1",
               OMPI_MCA_mpi_yield_when_idle="1")  # oversubscribed ranks yield when waiting
    extra = ["-log_view", f":{log}"] if log else []
    cmd = (mpirun() + ["-n", str(ranks), "/usr/bin/time", "-f", "PEAKRSS %M", PY, "-m",
                       "parjam"] + args + extra)
    t0 = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=code_dir)
    secs = time.perf_counter() - t0
    rss = [int(m) / 1024.0 for m in re.findall(r"PEAKRSS (\d+)", res.stderr)]
    if res.returncode:
        sys.stderr.write(res.stdout[-1500:] + res.stderr[-1500:])
    return rss, secs, res.returncode, res.stdout + res.stderr


def infog(text):
    """INFOG(i) values printed by -modes_eps_view (MB for the memory ones)."""
    out = {}
    for line in text.splitlines():
        m = re.match(r"\s*INFOG\((\d+)\) .*: (-?\d+)\s*$", line)
        if m and int(m.group(1)) in INFOG:
            out.setdefault(int(m.group(1)), int(m.group(2)))
    return out


def log_times(path):
    """(stages {name: seconds}, events {(stage, event): seconds}) of a -log_view file: the
    largest time over the ranks."""
    stages, events, stage = {}, {}, None
    with open(path) as fh:
        text = fh.read()
    for line in text.splitlines():
        if "Memory usage is given in bytes" in line:
            break
        m = re.match(r"^\s*\d+:\s+(.+):\s+(\d\.\d+e[+-]\d+)\s+\d", line)
        if m and stage is None:
            stages[m.group(1).strip()] = float(m.group(2))
            continue
        if line.startswith("--- Event Stage"):
            stage = line.split(":", 1)[1].strip()
            continue
        m = re.match(r"^(\S.*?)\s+(\d+)\s+\d+\.\d\s+(\d\.\d{4}e[+-]\d\d)\s", line)
        if stage is not None and m:
            key = (stage, m.group(1).strip())
            events[key] = events.get(key, 0.0) + float(m.group(3))
    return stages, events


def load():
    with open("/proc/loadavg") as fh:
        return fh.read().split()[0]


def weak(args, work, lines):
    lines += ["## 1. Weak scaling of `parjam modes --k %d` (MUMPS shift-and-invert)" % args.k, "",
              "Peak RSS per rank (MB, largest over the ranks; the smallest in brackets), the "
              "MUMPS factor's memory (INFOG, MB: 16/17 the analysis estimate on the most "
              "loaded rank / summed, 18 allocated at the factorisation on the most loaded "
              "rank, 21/22 effectively used, most loaded / summed), and the rest = peak RSS - "
              "INFOG(18) (what is not the factor: network, matrices, Krylov basis, Python, "
              "MPI). 'rest / P=1' is the rest against the same code's P = 1.", "",
              "| code | P | N | N/P | peak MB/rank | INFOG 16 / 17 | INFOG 18 | INFOG 21 / 22 "
              "| rest MB/rank | rest / P=1 | s | exit |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    base = {}
    checks = []
    for spec in args.weak:
        p, path = spec.split(":", 1)
        p = int(p)
        n = particles(path)
        outs = {}
        for name, code in (("old", args.old), ("new", ROOT)):
            out = os.path.join(work, f"weak-{name}-{p}.h5")
            rss, secs, rc, text = run(code, p, ["modes", os.path.abspath(path), "--k",
                                                str(args.k), "--method", "sinvert", "--out",
                                                out, "-q", "-modes_eps_view"])
            g = infog(text)
            rest = max(rss) - g.get(18, 0) if rss else float("nan")
            base.setdefault(name, rest)
            lines.append(
                f"| {name} | {p} | {n} | {n // p} | {max(rss):.0f} ({min(rss):.0f}) | "
                f"{g.get(16, '-')} / {g.get(17, '-')} | {g.get(18, '-')} | "
                f"{g.get(21, '-')} / {g.get(22, '-')} | {rest:.0f} | {rest / base[name]:.2f} | "
                f"{secs:.0f} | {rc} |")
            print(lines[-1], flush=True)
            outs[name] = out if rc == 0 else None
        if outs["old"] and outs["new"]:
            diffs, _ = differences(outs["old"], outs["new"], rtol=1e-6)
            same_particles = not [d for d in diffs if d.startswith("particles")
                                  or "active_particles" in d]
            checks.append(f"P = {p}: /particles/all and /modes/active_particles "
                          f"{'identical' if same_particles else 'DIFFER'}; other datasets "
                          f"differing beyond rtol 1e-6: "
                          f"{', '.join(d.split(':')[0] for d in diffs) or 'none'}")
    lines += ["", "Old against new output files (scripts/h5_same.py, run-dependent attributes "
              "such as seconds and the command line not compared):", ""]
    lines += [f"- {c}" for c in checks] + [""]


def particles(path):
    import h5py

    with h5py.File(path, "r") as f:
        return f["particles/all/diameter"].shape[0]


STRONG = {
    "analyze": lambda f, out: ["analyze", f],
    "dos --method kpm": lambda f, out: ["dos", "--method", "kpm", f, "--moments", "256",
                                        "--probes", "4", "--out", out],
    # the loose CG of bench_distributed_memory.py: the phases' times, not converged moduli
    "moduli (GAMG)": lambda f, out: ["moduli", f, "-moduli_pc_type", "gamg", "-moduli_ksp_rtol",
                                     "1e-4", "-moduli_ksp_max_it", "400", "-q"],
}


def strong(args, work, lines):
    runs = [(name, make, args.strong) for name, make in STRONG.items()]
    runs.append((f"modes --k {args.k}", lambda f, out: ["modes", f, "--k", str(args.k),
                                                         "--method", "sinvert", "--out", out,
                                                         "-q"], args.strong_modes))
    lines += ["## 2. Strong scaling 1 -> 2 ranks per log stage and event (this tree)", "",
              "Seconds from `-log_view` (largest over the ranks), events above 1 % of the run "
              "and parjam's own (reading rows, the active network, writing rows); "
              "an event is listed under its stage (events nest: they do not add up).", ""]
    for name, make, path in runs:
        n = particles(path)
        res = {}
        for p in (1, 2):
            log = os.path.join(work, f"strong-{name.split()[0]}-{p}.log")
            out = os.path.join(work, f"strong-{name.split()[0]}-{p}.h5")
            before = load()
            rss, secs, rc, _ = run(ROOT, p, make(os.path.abspath(path), out), log=log)
            stages, events = log_times(log) if os.path.exists(log) else ({}, {})
            res[p] = (rss, secs, rc, stages, events, before, load())
            print(f"{name} P={p}: {secs:.0f} s exit {rc} load {before}->{load()}", flush=True)
        lines += [f"### {name}, N = {n} ({dimension(path)}D)", "",
                  f"Wall time {res[1][1]:.0f} s on 1 rank (exit {res[1][2]}, load average "
                  f"{res[1][5]} -> {res[1][6]}), {res[2][1]:.0f} s on 2 (exit {res[2][2]}, "
                  f"load {res[2][5]} -> {res[2][6]}); peak RSS per rank "
                  f"{max(res[1][0] or [0]):.0f} MB and {max(res[2][0] or [0]):.0f} MB.", "",
                  "| stage / event | 1 rank s | 2 ranks s | speed-up |", "|---|---|---|---|"]
        total = sum(res[1][3].values()) or 1.0
        for stage in res[1][3]:
            t1, t2 = res[1][3][stage], res[2][3].get(stage, float("nan"))
            lines.append(f"| **stage {stage}** | {t1:.3g} | {t2:.3g} | {t1 / t2:.2f} |")
            for (st, ev), e1 in sorted(res[1][4].items(), key=lambda kv: -kv[1]):
                if st != stage or (e1 < 0.01 * total and not ev.startswith("parjam:")):
                    continue
                e2 = res[2][4].get((st, ev), float("nan"))
                lines.append(f"| {ev} | {e1:.3g} | {e2:.3g} | {e1 / e2:.2f} |")
        lines.append("")
        print("\n".join(lines[-12:]), flush=True)


def dimension(path):
    import h5py

    with h5py.File(path, "r") as f:
        return f["particles/all/position/value"].shape[-1]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--old", required=True, help="directory holding main's parjam package")
    ap.add_argument("--weak", nargs="*", default=[], help="P:PACKING per weak-scaling point")
    ap.add_argument("--strong", help="packing of the analysis strong-scaling runs (3D)")
    ap.add_argument("--strong-modes", help="packing of the modes strong-scaling run")
    ap.add_argument("--k", type=int, default=100)
    ap.add_argument("--out", default=os.path.join(ROOT, "docs", "bench-scaling-19.md"))
    args = ap.parse_args()
    work = tempfile.mkdtemp(prefix="bench19-")
    lines = ["# Modes and analysis scaling, memory per rank (issue 19)", "",
             f"Written by `scripts/bench_scaling_19.py` ({time.strftime('%Y-%m-%d %H:%M')} "
             f"UTC); every rank a process on this 2-core machine, shared with other jobs "
             f"(load average {load()} at the start). Packings tiled from small jammed ones "
             f"by `scripts/tile_packing.py`.", ""]
    if args.weak:
        weak(args, work, lines)
    if args.strong:
        strong(args, work, lines)
    lines.append(f"Load average at the end: {load()}.")
    with open(args.out, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
