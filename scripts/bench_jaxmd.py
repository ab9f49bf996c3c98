#!/usr/bin/env python3
"""parjam's FIRE quench against jax-md's FIRE on the same state, side by side in one run
(issue 18: "jax-md's FIRE (CPU, float64, neighbour list) on the same N = 4096 quench").

    source scripts/mpi-env
    python3 -m venv /tmp/jaxenv && /tmp/jaxenv/bin/pip install jax-md   # once (~600 MB)
    .venv/bin/python scripts/bench_jaxmd.py --jax-python /tmp/jaxenv/bin/python

The state: parjam's random start (``packing.random_packing``, 3D, monodisperse, harmonic,
N = --n, phi = --phi, --seed), written once to a temporary directory; every run starts from it.
Per round, in alternating order:

- parjam on 1 rank and on 2 ranks: ``fire.fire`` to max|F_i| < --ftol (parjam's default
  FIRE parameters);
- jax-md 0.2 (``minimize.fire_descent`` with its default parameters, float64, on the CPU;
  ``energy.soft_sphere_neighbor_list`` with alpha = 2, sigma = 1, epsilon = 1, which is parjam's
  V = (eps / alpha) (1 - r / sigma)^alpha), run by chunks of --chunk steps in one
  ``lax.fori_loop`` each, the neighbour list updated every step inside the loop and
  reallocated when it overflows, max|F_i| checked after each chunk, run to --jax-ftol (the
  issue's 1e-10); parjam's time is reported at that tolerance and at --ftol.  Compilation is
  timed separately (a first chunk on a copy of the state) and not counted.

jax runs with ``XLA_FLAGS=--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1``
(its process still runs a few helper threads: its CPU time can exceed its wall time), so that
1 rank of parjam meets about 1 core of jax-md.  Times: wall and process CPU (the slowest rank),
each the fastest of --rounds.  Writes docs/bench-jaxmd.md.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
OUT = os.path.join(ROOT, "docs", "bench-jaxmd.md")

JAX_WORKER = r'''
import importlib.metadata, json, os, sys, time
os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false "
                      "intra_op_parallelism_threads=1")
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax_md import energy, minimize, space

state, ftols, chunk, max_steps = sys.argv[1], json.loads(sys.argv[2]), int(sys.argv[3]), \
    int(sys.argv[4])
z = np.load(state)
R0, L = jnp.array(z["pos"]), float(z["L"])
disp, shift = space.periodic(L)
nfn, efn = energy.soft_sphere_neighbor_list(disp, L, sigma=1.0, epsilon=1.0, alpha=2.0,
                                            dr_threshold=0.2, capacity_multiplier=1.5)
force = jax.grad(lambda R, nbr: -efn(R, neighbor=nbr))
init, apply = minimize.fire_descent(lambda R, neighbor: efn(R, neighbor=neighbor), shift)

@jax.jit
def run_chunk(st, nbr):
    def body(i, c):
        st, nbr = c
        st = apply(st, neighbor=nbr)
        return st, nbr.update(st.position)
    st, nbr = lax.fori_loop(0, chunk, body, (st, nbr))
    f = force(st.position, nbr)
    return st, nbr, jnp.max(jnp.sqrt(jnp.sum(f * f, axis=1))), efn(st.position, neighbor=nbr)

def quench(R):
    nbr = nfn.allocate(R)
    st = init(R, neighbor=nbr)
    steps, out, fmax = 0, {}, np.inf
    while steps < max_steps:
        st2, nbr2, fm, e = run_chunk(st, nbr)
        if nbr2.did_buffer_overflow:
            nbr = nfn.allocate(st.position)
            continue
        st, nbr, fmax = st2, nbr2, float(fm)
        steps += chunk
        for t in ftols:
            if fmax < t and str(t) not in out:
                out[str(t)] = {"steps": steps, "wall": time.perf_counter() - t0,
                               "cpu": time.process_time() - c0, "energy": float(e)}
        if fmax < min(ftols):
            break
    return out, steps, fmax

t0, c0 = time.perf_counter(), time.process_time()
jax.block_until_ready(run_chunk(init(R0, neighbor=nfn.allocate(R0)), nfn.allocate(R0)))
compile_s = time.perf_counter() - t0
t0, c0 = time.perf_counter(), time.process_time()
out, steps, fmax = quench(R0)
print(json.dumps({"reached": out, "steps": steps, "fmax": fmax, "compile_s": compile_s,
                  "jax": jax.__version__, "jax_md": importlib.metadata.version("jax-md")}))
'''


def worker_parjam(a):
    """parjam's quench of the saved state on COMM_WORLD; prints JSON on rank 0."""
    import numpy as np
    from mpi4py import MPI
    from parjam import env
    from parjam.pack.fire import FireParams, fire
    from parjam.pack.forces import ForceField

    PETSc = env.petsc()
    z = np.load(a.state)
    pos, L = z["pos"], float(z["L"])
    ff = ForceField(PETSc.COMM_WORLD, np.ones(len(pos)), L, pos.shape[1], 2.0)
    ff.set_positions(pos)
    mpi = MPI.COMM_WORLD
    out = {}
    mpi.Barrier()
    t0, c0 = time.perf_counter(), time.process_time()
    steps = 0
    for tol in sorted(a.ftols, reverse=True):  # continue from the last tolerance
        r = fire(ff, tol, params=FireParams(max_steps=a.max_steps))
        steps += r.fire_steps
        cpu = mpi.allreduce(time.process_time() - c0, op=MPI.MAX)
        out[str(tol)] = {"steps": steps, "wall": time.perf_counter() - t0, "cpu": cpu,
                         "energy": r.energy, "status": r.status, "fmax": r.fmax}
    ff.destroy()
    if mpi.rank == 0:
        print(json.dumps({"reached": out}))


def run_parjam(a, ranks):
    cmd = os.environ.get("PARJAM_MPIRUN", "mpirun --oversubscribe").split() + [
        "-n", str(ranks), sys.executable, os.path.abspath(__file__), "--worker",
        "--state", a.state, "--max-steps", str(a.max_steps),
        "--ftols", *[str(t) for t in (a.ftol, a.jax_ftol)]]
    res = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


def run_jax(a):
    cmd = [a.jax_python, "-c", JAX_WORKER, a.state, json.dumps([a.jax_ftol]),
           str(a.chunk), str(a.max_steps)]
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    res = subprocess.run(cmd, capture_output=True, text=True, check=True, env=env)
    return json.loads(res.stdout.strip().splitlines()[-1])


def best(runs, tol, key):
    vals = [r["reached"][str(tol)][key] for r in runs if str(tol) in r["reached"]]
    return min(vals) if vals else None


def write(a, par1, par2, jax):
    def fmt(v, f="{:.1f}"):
        return "-" if v is None else f.format(v)

    rows = []
    for name, runs in (("parjam, 1 rank", par1), ("parjam, 2 ranks", par2),
                       ("jax-md, 1 thread", jax)):
        for tol in (a.jax_ftol, a.ftol):
            if name.startswith("jax") and tol != a.jax_ftol:
                continue
            rows.append((name, tol, best(runs, tol, "steps"), best(runs, tol, "wall"),
                         best(runs, tol, "cpu")))
    jw = best(jax, a.jax_ftol, "wall")
    lines = [
        f"## FIRE quench: parjam against jax-md (`scripts/bench_jaxmd.py`)", "",
        f"3D monodisperse harmonic spheres, N = {a.n}, phi = {a.phi}, parjam's random start "
        f"(seed {a.seed}); every run from the same saved state, {a.rounds} rounds alternating "
        f"parjam 1 rank / 2 ranks / jax-md; the fastest of the rounds.  jax-md "
        f"{jax[0].get('jax_md', '?')} (jax {jax[0].get('jax', '?')}), float64, CPU, one XLA thread, compile "
        f"{min(r['compile_s'] for r in jax):.1f} s not counted.  Machine: {a.note}", "",
        "| code | max abs F_i below | FIRE steps | wall s | CPU s (slowest rank) | "
        "jax-md wall / this wall (at 1e-10) |", "|---|---|---|---|---|---|"]
    for name, tol, steps, wall, cpu in rows:
        ratio = fmt(jw / wall, "{:.2f}") if (jw and wall and tol == a.jax_ftol) else "-"
        lines.append(f"| {name} | {tol:g} | {fmt(steps, '{:.0f}')} | {fmt(wall)} | "
                     f"{fmt(cpu)} | {ratio} |")
    lines.append("")
    with open(OUT, "w") as fh:
        fh.write("\n".join(lines))
    print("\n".join(lines))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--state", help=argparse.SUPPRESS)
    ap.add_argument("--ftols", type=float, nargs="+", help=argparse.SUPPRESS)
    ap.add_argument("--jax-python", help="python of a venv with jax-md installed")
    ap.add_argument("--n", type=int, default=4096)
    ap.add_argument("--phi", type=float, default=0.65)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--ftol", type=float, default=1e-13, help="parjam's tolerance")
    ap.add_argument("--jax-ftol", type=float, default=1e-10, help="the shared tolerance")
    ap.add_argument("--chunk", type=int, default=100, help="jax-md steps per jitted loop")
    ap.add_argument("--max-steps", type=int, default=400000)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--note", default="2 cores, shared", help="conditions, for the page")
    a = ap.parse_args()
    if a.worker:
        worker_parjam(a)
        return
    if not a.jax_python or not os.access(a.jax_python, os.X_OK):
        sys.exit("bench_jaxmd: give --jax-python, the python of a venv with jax-md")
    sys.path.insert(0, ROOT)
    import numpy as np
    from parjam.pack.packing import member_rng, random_packing

    with tempfile.TemporaryDirectory(prefix="bench-jaxmd-") as tmp:
        pk = random_packing(3, a.n, a.phi, 2.0, "mono", rng=member_rng(a.seed, 0))
        a.state = os.path.join(tmp, "state.npz")
        np.savez(a.state, pos=pk.pos, L=pk.L)
        par1, par2, jax = [], [], []
        for r in range(a.rounds):
            for name in (("p1", "p2", "jax") if r % 2 == 0 else ("jax", "p2", "p1")):
                if name == "jax":
                    jax.append(run_jax(a))
                else:
                    (par1 if name == "p1" else par2).append(run_parjam(a, int(name[1])))
                print(f"round {r}, {name}: done", flush=True)
    write(a, par1, par2, jax)


if __name__ == "__main__":
    main()
