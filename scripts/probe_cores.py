#!/usr/bin/env python3
"""What this machine gives a second core, before any code's parallel overhead: each workload
timed alone on one core, then as two independent copies on two cores at once (no MPI, no
communication, nothing shared but the machine; the two copies' timed parts start together
once both are set up), interleaved, repeated, medians.

    .venv/bin/python scripts/probe_cores.py --repeat 5 --n 8192 32768

Workloads (ns per iteration, or ms per FIRE step):

- ``alu``: four independent multiply-add chains in registers (the core itself);
- ``l2``: a random pointer chase through 1 MiB (one dependent load at a time, in L2);
- ``l3``: the same through 12 MiB (beyond L2: the shared cache or memory, and the page walks);
- ``dram``: a sum streamed over 512 MiB (memory bandwidth);
- ``fire N``: parjam's fused FIRE step (update, forces, exact sums; compiled kernels, one
  process, no MPI) on a random start of N particles (3D, monodisperse, harmonic, phi = 0.70):
  what one rank of a two-rank run computes at 2 N, without the halo, the ghosts or the wait.

"both / alone" is the slower copy's time over the lone copy's: the largest speed-up a second
core can give such a step is 2 / (both / alone).  The probes are compiled in a temporary
directory; nothing is written elsewhere.  Linux only (``taskset``).
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

PROBE_C = r"""
#include <stdio.h>
#include <stdlib.h>
#include <stdint.h>
#include <string.h>
#include <time.h>
static double now(void) { struct timespec t; clock_gettime(CLOCK_MONOTONIC, &t);
                          return t.tv_sec + 1e-9 * t.tv_nsec; }
static void ready(void) { /* set up: tell the parent, wait for its go (both copies start together) */
    char go[8];
    puts("ready");
    fflush(stdout);
    if (!fgets(go, sizeof go, stdin)) exit(1); }
static double chase(size_t bytes, long iters) {
    size_t n = bytes / sizeof(size_t), *a = malloc(n * sizeof(size_t)), p = 0;
    uint64_t s = 88172645463325252ull;
    for (size_t i = 0; i < n; i++) a[i] = i;
    for (size_t i = n - 1; i > 0; i--) { /* Sattolo's shuffle: one cycle through all */
        s ^= s << 13; s ^= s >> 7; s ^= s << 17;
        size_t j = s % i, t = a[i]; a[i] = a[j]; a[j] = t; }
    ready();
    double t0 = now();
    for (long k = 0; k < iters; k++) p = a[p];
    double t = now() - t0;
    if (p == (size_t)-1) puts("");
    free(a);
    return 1e9 * t / iters; }
int main(int argc, char **argv) {
    const char *w = argv[1]; double ns = 0;
    if (!strcmp(w, "alu")) {
        double x0 = 1, x1 = 2, x2 = 3, x3 = 4, a = 0.999999, b = 1e-9; long it = 400000000;
        ready();
        double t0 = now();
        for (long k = 0; k < it; k++) { x0 = x0*a + b; x1 = x1*a + b; x2 = x2*a + b; x3 = x3*a + b; }
        ns = 1e9 * (now() - t0) / it;
        if (x0 + x1 + x2 + x3 == 0) puts("");
    } else if (!strcmp(w, "l2")) ns = chase(1 << 20, 100000000);
    else if (!strcmp(w, "l3")) ns = chase(12 << 20, 30000000);
    else if (!strcmp(w, "dram")) {
        size_t n = (size_t)64 << 20; double *a = malloc(n * 8), s = 0;
        for (size_t i = 0; i < n; i++) a[i] = (double)i;
        ready();
        double t0 = now();
        for (int r = 0; r < 5; r++) for (size_t i = 0; i < n; i++) s += a[i];
        ns = 1e9 * (now() - t0) / (5.0 * n);
        if (s == 0) puts("");
        free(a);
    }
    printf("%.4f\n", ns);
    return 0; }
"""


def fire_worker(n, steps):
    """ms per fused FIRE step on a random start of n particles (this process, one core)."""
    from parjam.pack import cellsearch, kernels
    from parjam.pack.randomstart import random_packing

    pack = random_packing(3, n, 0.70, 2.0, "mono", 1.4, np.random.default_rng(0))
    x, diam, L = pack.pos.copy(), pack.diam.copy(), pack.L
    pi, pj = cellsearch.cell_pair_lists(np.mod(x, L), L, diam.max() + 0.2 * diam.min(), 0, n)
    v, f, ref = np.zeros_like(x), np.zeros_like(x), x.copy()
    acc = np.zeros(kernels.FIRE_ACC, dtype=np.int64)
    step = kernels.FIRE_UPDATE | kernels.FIRE_FORCES

    def call(mode):
        kernels.fire_step(mode, x, v, f, ref, L, 0.01, 0, 0.0, 0.99, 0.001, 0.0, pi, pj, x,
                          diam, 2.0, 1.0, 0, n, acc)

    call(kernels.FIRE_FORCES)
    print("ready", flush=True)  # set up: wait for the parent's go (both copies start together)
    sys.stdin.readline()
    t = time.perf_counter()
    for _ in range(steps):
        call(step)
    return 1e3 * (time.perf_counter() - t) / steps


def command(work, exe, steps):
    if work.startswith("fire"):
        return [sys.executable, os.path.abspath(__file__), "--worker", work.split()[1],
                "--steps", str(steps)]
    return [exe, work]


def run(cmds):
    """Start the commands (each pinned to its core), let their timed parts begin together once
    all are set up (each prints "ready" and waits for a line); their printed numbers."""
    procs = [subprocess.Popen(["taskset", "-c", str(core)] + cmd, stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True) for core, cmd in cmds]
    for p in procs:
        if p.stdout.readline().strip() != "ready":
            raise SystemExit("a probe failed before its timed part")
    for p in procs:
        p.stdin.write("go\n")
        p.stdin.flush()
    out = [p.communicate()[0] for p in procs]
    if any(p.returncode for p in procs):
        raise SystemExit(f"a probe failed: {[p.returncode for p in procs]}")
    return [float(o.split()[-1]) for o in out]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--n", type=int, nargs="*", default=[8192, 32768],
                    help="particles of the FIRE-step probes (one copy each)")
    ap.add_argument("--steps", type=int, default=400, help="FIRE steps per probe")
    ap.add_argument("--json", help="also write the raw times here")
    ap.add_argument("--worker", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        print(f"{fire_worker(args.worker, args.steps):.6f}")
        return
    if os.cpu_count() < 2:
        raise SystemExit("probe_cores needs two cores")
    works = ["alu", "l2", "l3", "dram"] + [f"fire {n}" for n in args.n]
    with tempfile.TemporaryDirectory(prefix="parjam-cores-") as tmp:
        src, exe = os.path.join(tmp, "probe.c"), os.path.join(tmp, "probe")
        with open(src, "w") as fh:
            fh.write(PROBE_C)
        subprocess.run(["cc", "-O2", "-o", exe, src], check=True)
        times = {w: {"alone": [], "both": []} for w in works}
        print(f"load average {os.getloadavg()[0]:.2f}", flush=True)
        for r in range(args.repeat):
            for w in works:
                cmd = command(w, exe, args.steps)
                times[w]["alone"] += run([(1, cmd)])
                times[w]["both"].append(max(run([(0, cmd), (1, cmd)])))
            print(f"round {r + 1} of {args.repeat} done", flush=True)
        print(f"load average {os.getloadavg()[0]:.2f}")
    print("\n| workload | unit | alone | both at once (slower copy) | both / alone | "
          "ceiling of a second core |")
    print("|---|---|---|---|---|---|")
    for w in works:
        a, b = np.median(times[w]["alone"]), np.median(times[w]["both"])
        ratios = np.array(times[w]["both"]) / np.array(times[w]["alone"])
        unit = "ms/step" if w.startswith("fire") else "ns"
        print(f"| {w} | {unit} | {a:.3f} | {b:.3f} | {np.median(ratios):.3f} "
              f"({ratios.min():.2f} - {ratios.max():.2f}) | {2 / np.median(ratios):.2f}x |")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(times, fh, indent=1)


if __name__ == "__main__":
    main()
