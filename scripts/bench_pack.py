#!/usr/bin/env python3
"""Benchmark: making one jammed 3D packing, parjam (1 and 2 ranks) against a plain numpy/scipy
FIRE, side by side in one run.  Writes a markdown section (default docs/bench-pack.md).

Tasks, all from the same random start (seed, member 0):
  A. quench at phi = phi_c + 1e-2 to max|F| <= 1e-12: plain FIRE vs `parjam pack --phi`;
  B. the full protocol, phi_c bisection then phi_c + dphi (default 1e-4), max|F| <= 1e-13:
     `parjam pack --dphi` on 1 and 2 ranks (the plain FIRE is not run through the bisection:
     task A alone already costs it minutes).
Each run is a separate process; time is wall clock, memory the peak RSS of the largest process.

    .venv/bin/python scripts/bench_pack.py --n 4096
"""

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time

import h5py
import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def plain_fire(pos, diam, L, ftol, max_steps=2_000_000):
    """A plain numpy/scipy FIRE (periodic k-d tree every step, harmonic contacts): the baseline."""
    from scipy.spatial import cKDTree

    def forces(x):
        x = x % L
        pairs = cKDTree(x, boxsize=L).query_pairs(diam.max(), output_type="ndarray")
        i, j = pairs[:, 0], pairs[:, 1]
        dr = x[j] - x[i]
        dr -= L * np.rint(dr / L)
        r = np.linalg.norm(dr, axis=1)
        s = 0.5 * (diam[i] + diam[j])
        c = r < s
        i, j, dr, r, s = i[c], j[c], dr[c], r[c], s[c]
        fmag = (1.0 - r / s) / s
        fij = (fmag / r)[:, None] * dr
        F = np.zeros_like(x)
        np.add.at(F, j, fij)
        np.add.at(F, i, -fij)
        return F

    x = pos.copy()
    v = np.zeros_like(x)
    F = forces(x)
    dt, dt_max, a, n_pos = 0.05, 0.5, 0.1, 0
    for step in range(1, max_steps + 1):
        if np.sqrt((F * F).sum(axis=1)).max() < ftol:
            return x % L, step
        P = (F * v).sum()
        if P > 0:
            n_pos += 1
            if n_pos > 5:
                dt, a = min(dt * 1.1, dt_max), a * 0.99
        else:
            n_pos, dt, a = 0, dt * 0.5, 0.1
            x -= 0.5 * dt * v
            v[:] = 0.0
        v += dt * F
        vn, fn = np.linalg.norm(v), np.linalg.norm(F)
        if fn > 0:
            v = (1 - a) * v + a * vn / fn * F
        x += dt * v
        F = forces(x)
    return x % L, max_steps


def measure(cmd, env=None):
    """Run cmd in a wrapper process; return (seconds, peak RSS in MiB of its largest process)."""
    wrapper = ("import resource, subprocess, sys, time, json; t = time.time(); "
               "rc = subprocess.call(sys.argv[1:]); "
               "print(json.dumps([rc, time.time() - t, "
               "resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024]))")
    out = subprocess.run([sys.executable, "-c", wrapper, *cmd], capture_output=True, text=True,
                         env=env)
    rc, secs, mib = json.loads(out.stdout.strip().splitlines()[-1])
    if rc != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{out.stderr[-2000:]}")
    return secs, mib


def parjam_cmd(ranks, args):
    exe = [os.path.join(ROOT, ".venv", "bin", "parjam")]
    if ranks == 1:
        return exe + args
    return ["mpirun", "--oversubscribe", "-n", str(ranks)] + exe + args


def read_params(path):
    from parjam.files import h5md

    with h5py.File(path) as f:
        return dict(f["parameters"].attrs), float(h5md.observable(f, "max_force"))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=4096)
    ap.add_argument("--dphi", type=float, default=1e-4)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--skip-baseline", action="store_true")
    ap.add_argument("--out", default=os.path.join(ROOT, "docs", "bench-pack.md"))
    a = ap.parse_args()
    env = dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
               OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    work = tempfile.mkdtemp(prefix="bench-pack-")
    base = ["pack", "--dim", "3", "--n", str(a.n), "--seed", str(a.seed), "-q"]

    # B: full protocol on 1 and 2 ranks (also gives phi_c for task A)
    full = {}
    for ranks in (1, 2):
        out = os.path.join(work, f"full{ranks}")
        secs, mib = measure(parjam_cmd(ranks, base + ["--dphi", str(a.dphi), "--out", out]), env)
        params, fmax = read_params(os.path.join(out, f"member0000_dphi{a.dphi:.1e}.h5"))
        full[ranks] = (secs, mib, params, fmax)
        print(f"full protocol, {ranks} rank(s): {secs:.1f} s, {mib:.0f} MiB", flush=True)
    phi_c = float(full[1][2]["phi_c"])
    phi_q = phi_c + 1e-2

    # A: quench at phi_c + 1e-2, parjam on 1 and 2 ranks
    quench = {}
    for ranks in (1, 2):
        out = os.path.join(work, f"q{ranks}")
        secs, mib = measure(parjam_cmd(ranks, base + ["--phi", repr(phi_q), "--ftol", "1e-12",
                                                      "--out", out]), env)
        params, fmax = read_params(os.path.join(out, f"member0000_phi{phi_q:.4f}.h5"))
        quench[ranks] = (secs, mib, params, fmax)
        print(f"quench, {ranks} rank(s): {secs:.1f} s", flush=True)

    # A: the plain FIRE, same start, in its own process
    if not a.skip_baseline:
        code = (f"import sys; sys.path.insert(0, {ROOT!r}); sys.path.insert(0, {os.path.dirname(__file__)!r});"
                f"import numpy as np, bench_pack as b, time, json;"
                f"from parjam.pack.packing import random_packing; from parjam.pack.packing import member_rng;"
                f"p = random_packing(3, {a.n}, 0.66, 2.0, 'mono', 1.4, member_rng({a.seed}, 0));"
                f"p = p.rescaled({phi_q!r}); t = time.time();"
                f"x, steps = b.plain_fire(p.pos, p.diam, p.L, 1e-12);"
                f"print(json.dumps([steps, time.time() - t]))")
        wrapper_out = subprocess.run([sys.executable, "-c", code], capture_output=True,
                                     text=True, env=env)
        steps, secs_fire = json.loads(wrapper_out.stdout.strip().splitlines()[-1])
        print(f"plain FIRE: {secs_fire:.1f} s, {steps} steps", flush=True)
    else:
        steps, secs_fire = None, None

    write_report(a, full, quench, (steps, secs_fire), phi_c)


def write_report(a, full, quench, baseline, phi_c):
    steps, secs_fire = baseline
    lines = [
        f"## Packing generation (`scripts/bench_pack.py --n {a.n}`)",
        "",
        f"3D monodisperse, harmonic, N = {a.n}, seed {a.seed}; {platform.node()}, "
        f"{time.strftime('%Y-%m-%d')}; all runs in one session, one after another (ratios are "
        "what to read: the machine is shared). phi_c = "
        f"{phi_c:.10f}.",
        "",
        "| task | code | ranks | wall time (s) | peak RSS per process (MiB) | FIRE steps | Newton steps | force evaluations | max F |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for ranks, (secs, mib, p, fmax) in full.items():
        lines.append(f"| bisection + dphi = {a.dphi:g} | parjam | {ranks} | {secs:.1f} | {mib:.0f} | "
                     f"{p['fire_steps']} | {p['newton_steps']} | {p['force_evaluations']} | {fmax:.1e} |")
    for ranks, (secs, mib, p, fmax) in quench.items():
        lines.append(f"| quench at phi_c + 1e-2 | parjam | {ranks} | {secs:.1f} | {mib:.0f} | "
                     f"{p['fire_steps']} | {p['newton_steps']} | {p['force_evaluations']} | {fmax:.1e} |")
    if secs_fire is not None:
        lines.append(f"| quench at phi_c + 1e-2 | plain numpy FIRE | 1 | {secs_fire:.1f} | - | "
                     f"{steps} | 0 | {steps} | < 1e-12 |")
        lines += ["", "Ratios (plain FIRE time / parjam time):", ""]
        for ranks in (1, 2):
            lines.append(f"- quench, {ranks} rank(s): {secs_fire / quench[ranks][0]:.1f}x; "
                         f"plain FIRE quench / parjam full protocol (bisection + ladder): "
                         f"{secs_fire / full[ranks][0]:.1f}x")
    if secs_fire is not None:
        per_step = secs_fire / steps
        lines += ["", "The plain FIRE is not run through the bisection (hours at this N). A lower bound "
                  "for it: its measured cost per step times the FIRE steps parjam needed for the "
                  "same protocol (the plain FIRE has no Newton steps, so it needs more):", ""]
        for ranks, (secs, mib, p, fmax) in full.items():
            bound = per_step * p["fire_steps"]
            lines.append(f"- full protocol, {ranks} rank(s): plain FIRE >= {bound:.0f} s "
                         f"({p['fire_steps']} steps x {per_step * 1e3:.2f} ms), parjam "
                         f"{secs:.1f} s: >= {bound / secs:.1f}x")
        lines.append("")
    for ranks, (secs, mib, p, fmax) in quench.items():
        per = secs / max(p["force_evaluations"], 1) / a.n * 1e9
        lines.append(f"- parjam quench, {ranks} rank(s): {per:.0f} ns per particle per force "
                     "evaluation (whole run divided by evaluations: an upper bound)")
    text = "\n".join(lines) + "\n"
    with open(a.out, "w") as fh:
        fh.write(text)
    print(text)


if __name__ == "__main__":
    main()
