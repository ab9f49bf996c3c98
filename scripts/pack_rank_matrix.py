#!/usr/bin/env python3
"""The same `parjam pack` member on 1, 2, 3 and 4 ranks: are the files bitwise the same?

    source scripts/mpi-env
    nice .venv/bin/python scripts/pack_rank_matrix.py --n 2048 --json bench-out/rank-matrix.json

For each N, dimension, dispersity and protocol (a quench at fixed phi; the O'Hern bisection with
its refinement and one state above phi_c; the extrapolation from a jammed start with a ladder
of two states) it runs `parjam pack --members 1` on each rank count (one member shared by all
ranks: the distributed minimisation), compares every file with the one-rank run's
(parjam.testing.h5compare: every dataset and parameter, provenance and wall times aside) and
records the FIRE and Newton steps and the wall time.  Ranks above the cores are oversubscribed
(`mpirun --oversubscribe`): correctness, not speed.  Writes JSON and prints a table.
"""

import argparse
import glob
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

PHI = {2: "0.88", 3: "0.70"}
PROTOCOLS = {
    "quench": lambda d: ["--phi", PHI[d]],
    "bisection": lambda d: ["--dphi", "1e-4"],
    "ladder": lambda d: ["--phic-method", "extrapolate", "--dphi", "1e-3", "1e-2"],
}


def run(out, args, ranks):
    mpirun = os.environ.get("PARJAM_MPIRUN", "mpirun --oversubscribe").split()
    cmd = [sys.executable, "-m", "parjam", "pack", *args, "--out", out, "-q",
           "--checkpoint-every", "0"]
    if ranks > 1:
        cmd = mpirun + ["-n", str(ranks)] + cmd
    env = dict(os.environ, PYTHONPATH=ROOT, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    t = time.perf_counter()
    r = subprocess.run(cmd, env=env, capture_output=True, text=True)
    return r, time.perf_counter() - t


def steps(path):
    import h5py

    with h5py.File(path, "r") as f:
        p = f["parameters"].attrs
        return {k: int(p[k]) for k in ("fire_steps", "newton_steps", "escapes", "cycles")
                if k in p}


def main():
    from parjam.testing.h5compare import differences

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="+", default=[2048])
    ap.add_argument("--dim", type=int, nargs="+", default=[2, 3])
    ap.add_argument("--dispersity", nargs="+", default=["mono", "bi"])
    ap.add_argument("--protocol", nargs="+", default=list(PROTOCOLS), choices=list(PROTOCOLS))
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2, 3, 4])
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--json", default=None)
    ap.add_argument("--keep", default=None, help="keep the files under this directory")
    args = ap.parse_args()
    base = args.keep or tempfile.mkdtemp(prefix="parjam-matrix-")
    rows = []
    if args.json and os.path.exists(args.json):  # continue an interrupted matrix
        with open(args.json) as f:
            rows = json.load(f)["rows"]
    done = {(r["n"], r["dim"], r["dispersity"], r["protocol"]) for r in rows}
    for n in args.n:
        for d in args.dim:
            for disp in args.dispersity:
                for proto in args.protocol:
                    if (n, d, disp, proto) in done:
                        continue
                    pack_args = ["--dim", str(d), "--n", str(n), "--dispersity", disp,
                                 "--seed", str(args.seed), *PROTOCOLS[proto](d)]
                    row = {"n": n, "dim": d, "dispersity": disp, "protocol": proto,
                           "args": pack_args, "runs": {}}
                    ref = None
                    for p in args.ranks:
                        out = os.path.join(base, f"N{n}_d{d}_{disp}_{proto}_P{p}")
                        shutil.rmtree(out, ignore_errors=True)
                        r, wall = run(out, pack_args, p)
                        files = sorted(glob.glob("*.h5", root_dir=out))
                        info = {"ok": r.returncode == 0, "wall_s": round(wall, 1),
                                "files": files, "load": os.getloadavg()[0]}
                        if r.returncode != 0:
                            info["error"] = r.stderr.strip().splitlines()[-1:]
                        elif ref is None:
                            ref = out
                            info["steps"] = {f: steps(os.path.join(out, f)) for f in files}
                        else:
                            info["differences"] = {
                                f: differences(os.path.join(ref, f), os.path.join(out, f))
                                for f in files}
                            info["bitwise"] = (files == row["runs"][1]["files"] and not any(
                                info["differences"].values()))
                        row["runs"][p] = info
                        print(f"N = {n} d = {d} {disp} {proto} P = {p}: "
                              f"{'ok' if info['ok'] else 'FAILED'} {wall:.0f} s"
                              + (f" bitwise = {info.get('bitwise')}" if p > 1 else ""),
                              flush=True)
                    rows.append(row)
                    if args.json:
                        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
                        with open(args.json, "w") as f:
                            json.dump({"rows": rows}, f, indent=1, default=str)
    print("| N | d | dispersity | protocol | FIRE steps | Newton steps | "
          + " | ".join(f"{p} ranks" for p in args.ranks[1:]) + " |")
    for row in rows:
        runs = {int(k): v for k, v in row["runs"].items()}
        st = runs[args.ranks[0]].get("steps", {})
        fire = max(s.get("fire_steps", 0) for s in st.values()) if st else "-"
        newton = max(s.get("newton_steps", 0) for s in st.values()) if st else "-"
        cells = ["bitwise" if runs[p].get("bitwise") else
                 ("FAILED" if not runs[p]["ok"] else "differs") for p in args.ranks[1:]]
        print(f"| {row['n']} | {row['dim']} | {row['dispersity']} | {row['protocol']} | "
              f"{fire} | {newton} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
