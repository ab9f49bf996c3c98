#!/usr/bin/env python3
"""How the cost of a packing at dphi grows with N: the FIRE and Newton steps of every
minimisation of `parjam pack --phic-method extrapolate --phi-start 0.70 --dphi DPHI` (3D
monodisperse by default; --dim 2 --dispersity bi for 2D; harmonic), per N and seed, one rank
per run.

Step counts do not depend on the machine's load, so several runs may share the cores (their wall
times then do).  Each finished run is appended as one JSON line to --json; --report reads that
file and writes the table, the fitted growth law (total steps ~ N^b) and its extrapolation to
the sizes asked for (markdown, to --out or stdout).

    .venv/bin/python scripts/pack_steps.py --n 1024 2048 4096 --seeds 1 2 3 4
    .venv/bin/python scripts/pack_steps.py --report --extrapolate 100000
"""

import argparse
import json
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
DEFAULT_JSON = os.path.join(ROOT, "bench-out", "pack-steps.jsonl")


class Recorder:
    """Wraps parjam.pack.minimize's fire/newton/minimise to log every round of every minimisation."""

    def __init__(self):
        from parjam.pack import minimize

        self.mod = minimize
        self.orig = (minimize.fire, minimize.newton, minimize.minimize)
        self.calls = []

    def _round(self, kind, fn):
        def wrapped(ff, ftol, *a, **k):
            t = time.perf_counter()
            r = fn(ff, ftol, *a, **k)
            steps = r.fire_steps if kind == "fire" else r.newton_steps
            self.calls[-1]["rounds"].append({"kind": kind, "tol": ftol, "steps": steps,
                                             "status": r.status, "fmax": r.fmax,
                                             "t": time.perf_counter() - t})
            return r
        return wrapped

    def _minimise(self, ff, *a, **k):
        self.calls.append({"rounds": [], "L": float(ff.L)})
        t = time.perf_counter()
        r = self.orig[2](ff, *a, **k)
        self.calls[-1].update(status=r.status, fire=r.fire_steps, newton=r.newton_steps,
                              t=time.perf_counter() - t)
        return r

    def __enter__(self):
        self.mod.fire = self._round("fire", self.orig[0])
        self.mod.newton = self._round("newton", self.orig[1])
        self.mod.minimize = self._minimise
        return self

    def __exit__(self, *exc):
        self.mod.fire, self.mod.newton, self.mod.minimize = self.orig


def run_one(n, seed, dphi, phi_start, dim=3, dispersity="mono", tail_dof=None, variant=None):
    from parjam import env
    from parjam.pack import minimize
    from parjam.pack import fire as fire_mod

    if variant is not None:  # A/B of the FIRE variants (parjam.pack.fire.DEFAULT_VARIANT)
        fire_mod.DEFAULT_VARIANT = variant

    PETSc = env.petsc()
    from parjam.pack.packing import member_rng
    from parjam.pack.packing import Jammer, random_packing

    if tail_dof is not None:  # A/B of FIRE's tail against Newton's (minimize.FIRE_TAIL_DOF)
        minimize.FIRE_TAIL_DOF = tail_dof
    pack = random_packing(dim, n, phi_start, dispersity=dispersity, rng=member_rng(seed, 0))
    t0 = time.perf_counter()
    with Recorder() as rec:
        jam = Jammer(PETSc.COMM_SELF, pack)
        try:
            st = jam.find_phi_c_from_above(dphi)
            phi_c = st.info["phi_c"]
            jam.ladder(phi_c, [dphi])
            fire, newton = jam.total_fire, jam.total_newton
            # neighbour-list rebuilds per force evaluation: the replicated part of a FIRE step
            rebuilds, force_calls = jam.ff.n_rebuilds, jam.ff.n_force_calls
        finally:
            jam.destroy()
    return {"n": n, "seed": seed, "dphi": dphi, "phi_start": phi_start, "phi_c": phi_c,
            "dim": dim, "dispersity": dispersity, "fire_tail_dof": minimize.FIRE_TAIL_DOF,
            "variant": fire_mod.DEFAULT_VARIANT,
            "fire": fire, "newton": newton, "rebuilds": rebuilds, "force_calls": force_calls,
            "t": time.perf_counter() - t0, "calls": rec.calls}


def load(path):
    with open(path) as fh:
        return [json.loads(line) for line in fh if line.strip()]


def fit(rows):
    """Least-squares fit of log(mean total FIRE steps) against log N: (b, a) of steps = a N^b."""
    ns = sorted({r["n"] for r in rows})
    means = [np.mean([r["fire"] for r in rows if r["n"] == n]) for n in ns]
    b, loga = np.polyfit(np.log(ns), np.log(means), 1)
    return b, np.exp(loga)


def report(rows, extrapolate):
    ns = sorted({r["n"] for r in rows})
    out = ["| N | seeds | FIRE steps, total (mean, range) | of which minimisation 3 "
           "| after a Newton saddle exit | Newton steps | phi_c (mean) |",
           "|---|---|---|---|---|---|---|"]
    for n in ns:
        rs = [r for r in rows if r["n"] == n]
        tot = np.array([r["fire"] for r in rs])
        third = np.mean([r["calls"][2]["fire"] if len(r["calls"]) > 2 else 0 for r in rs])
        later = np.mean([sum(x["steps"] for c in r["calls"] for x in c["rounds"][1:]
                             if x["kind"] == "fire") for r in rs])
        out.append(f"| {n} | {len(rs)} | {tot.mean():,.0f} ({tot.min():,} - {tot.max():,}) "
                   f"| {third:,.0f} | {later:,.0f} | {np.mean([r['newton'] for r in rs]):.0f} "
                   f"| {np.mean([r['phi_c'] for r in rs]):.5f} |")
    b, a = fit(rows)
    out.append("")
    out.append(f"Fit over N = {ns[0]}..{ns[-1]}: total FIRE steps ~ {a:.3g} N^{b:.2f}.")
    for n in extrapolate:
        out.append(f"- N = {n}: {a * n ** b:,.0f} FIRE steps expected.")
    return "\n".join(out) + "\n"


def compare(rows):
    """FIRE against FIRE 2.0 on the same (N, seed): total FIRE and Newton steps and wall time of
    the whole protocol, per N (means over the seeds that ran both) and the ratio fire2 / fire
    of the FIRE steps (geometric mean over seeds, with its range)."""
    by = {}
    for r in rows:
        by.setdefault((r["n"], r["seed"]), {})[r.get("variant", "fire")] = r
    out = ["| N | seeds | FIRE steps: FIRE | FIRE 2.0 | ratio 2.0 / FIRE (geo. mean, range) "
           "| Newton steps: FIRE | FIRE 2.0 | wall s: FIRE | FIRE 2.0 |",
           "|---|---|---|---|---|---|---|---|---|"]
    for n in sorted({k[0] for k in by}):
        pairs = [v for k, v in by.items() if k[0] == n and {"fire", "fire2"} <= set(v)]
        if not pairs:
            continue
        a = np.array([[p["fire"]["fire"], p["fire2"]["fire"]] for p in pairs], dtype=float)
        nw = np.array([[p["fire"]["newton"], p["fire2"]["newton"]] for p in pairs], dtype=float)
        t = np.array([[p["fire"]["t"], p["fire2"]["t"]] for p in pairs])
        ratio = a[:, 1] / a[:, 0]
        out.append(f"| {n} | {len(pairs)} | {a[:, 0].mean():,.0f} | {a[:, 1].mean():,.0f} "
                   f"| {np.exp(np.log(ratio).mean()):.2f} ({ratio.min():.2f} - {ratio.max():.2f}) "
                   f"| {nw[:, 0].mean():.0f} | {nw[:, 1].mean():.0f} | {t[:, 0].mean():.0f} "
                   f"| {t[:, 1].mean():.0f} |")
    return "\n".join(out) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="*", default=[1024, 2048, 4096])
    ap.add_argument("--seeds", type=int, nargs="*", default=[1, 2, 3, 4])
    ap.add_argument("--dphi", type=float, default=1e-3)
    ap.add_argument("--phi-start", type=float, default=0.70)
    ap.add_argument("--dim", type=int, default=3, choices=(2, 3))
    ap.add_argument("--dispersity", default="mono",
                    help="mono or bi (2D needs bi: mono crystallises)")
    ap.add_argument("--fire-tail-dof", type=int, default=None,
                    help="override minimize.FIRE_TAIL_DOF (e.g. 10**9: Newton's tail at every N)")
    ap.add_argument("--fire", default=None, choices=("fire", "fire2"),
                    help="FIRE variant (default: parjam.pack.fire.DEFAULT_VARIANT)")
    ap.add_argument("--json", default=DEFAULT_JSON)
    ap.add_argument("--report", action="store_true", help="only summarise --json")
    ap.add_argument("--compare", action="store_true",
                    help="only tabulate FIRE against FIRE 2.0 from --json (runs with --fire)")
    ap.add_argument("--extrapolate", type=int, nargs="*", default=[100000])
    ap.add_argument("--out", default=None, help="markdown file for --report (default stdout)")
    a = ap.parse_args()
    if not (a.report or a.compare):
        os.makedirs(os.path.dirname(os.path.abspath(a.json)), exist_ok=True)
        for n in a.n:
            for seed in a.seeds:
                rec = run_one(n, seed, a.dphi, a.phi_start, a.dim, a.dispersity,
                              a.fire_tail_dof, a.fire)
                print(f"N = {n} seed {seed} {rec['variant']}: {rec['fire']} FIRE steps, "
                      f"{rec['newton']} Newton steps, {rec['t']:.1f} s, "
                      f"phi_c = {rec['phi_c']:.8f}", flush=True)
                with open(a.json, "a") as fh:
                    fh.write(json.dumps(rec) + "\n")
        return
    text = compare(load(a.json)) if a.compare else report(load(a.json), a.extrapolate)
    if a.out:
        with open(a.out, "w") as fh:
            fh.write(text)
    else:
        sys.stdout.write(text)


if __name__ == "__main__":
    main()
