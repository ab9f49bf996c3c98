#!/usr/bin/env python3
"""The measurements of docs/explanation/reliability.md "Honest at the extremes" and docs/results/reproduction.md
"p / dphi down to 1e-10".

    scripts/extremes.py pdphi  --dim 3 --n 64 256 --seeds 4 --out bench-out/pdphi-3d.jsonl
    scripts/extremes.py census --dim 3 --n 1024 --members 20 --dphi 1e-9 1e-8 1e-6 \
                               --out bench-out/census.jsonl
    scripts/extremes.py report bench-out/pdphi-*.jsonl bench-out/census*.jsonl \
                               --img docs/img/pdphi.png

pdphi: one member per (N, seed) made as ``parjam pack`` makes it (bisection, phi_c refined from
the jammed side, compression ladder, every state stabilised), the ladder dphi = 1e-10 .. 1e-1;
per state p, the virial dphi, Nc - Nc_iso, stability; per member the resolution of phi_c and
the offset of the bisection's phi_c (the label error of the old protocol, whose phi_c was the
bisection's: its states at "dphi" sat at dphi + offset).
census: per state the stability check before (after force balance, before any escape) and
after, Nc - Nc_iso, escapes, and the time spent in the check and escapes per member.
report: markdown tables (stdout) and the p/dphi plot.
files: the same census table from packing files already written (e.g. a `parjam run`'s pack
stage: scripts/extremes.py files results/paper-3d/stages/pack-*/member*.h5).
Each finished member is appended as a JSON line at once (a killed run keeps what it did).
"""

import argparse
import json
import sys
import time

import numpy as np


def member(d, n, seed, m, dphis, alpha):
    from parjam import env
    from parjam.net.network import analyze
    from parjam.pack.packing import Jammer, LadderUnjammed, member_rng, random_packing

    PETSc = env.petsc()
    disp = "bi" if d == 2 else "mono"
    pack = random_packing(d, n, {2: 0.86, 3: 0.66}[d], alpha, disp, 1.4, member_rng(seed, m))
    jam = Jammer(PETSc.COMM_SELF, pack)
    spent = {"stabilise": 0.0, "cycle": 0.0}
    real, real_cycle = jam.stabilise, jam.compression_cycle

    def timed(res, e_stop=-np.inf, phi=None):
        t = time.perf_counter()
        try:
            return real(res, e_stop, phi)
        finally:
            spent["stabilise"] += time.perf_counter() - t

    def timed_cycle(phi, factor, e_stop=-np.inf):
        t = time.perf_counter()
        try:
            return real_cycle(phi, factor, e_stop)
        finally:
            spent["cycle"] += time.perf_counter() - t

    jam.stabilise, jam.compression_cycle = timed, timed_cycle
    t0 = time.perf_counter()
    try:
        bis = jam.find_phi_c()
        found = jam.refine_phi_c(min(dphis))
        phi_c = found["phi_c"]
        unjammed_at = None
        try:
            states = jam.ladder(phi_c, dphis)
        except LadderUnjammed as exc:  # kept, as parjam pack keeps them
            states, unjammed_at = exc.states, exc.step
            print(f"  {exc}", flush=True)
    finally:
        jam.destroy()
    rows = []
    for st in [bis] + states:
        net = analyze(st.pack)
        rows.append({k: (float(v) if isinstance(v, (float, np.floating)) else
                         int(v) if isinstance(v, (int, np.integer)) else v)
                     for k, v in {
                         "state": st.label, "dphi": st.pack.phi - phi_c,
                         "dphi_label": st.info.get("dphi", np.nan),
                         "dphi_virial": st.info.get("dphi_virial", np.nan),
                         "p": net.pressure, "excess": net.excess, "max_force": net.max_force,
                         **{k: st.info[k] for k in ("stable", "negative_curvatures_found",
                                                    "excess_found", "escapes", "cycles",
                                                    "negative_curvatures") if k in st.info},
                     }.items()})
    return {"d": d, "n": n, "seed": seed, "member": m, "alpha": alpha, "phi_c": phi_c,
            "phi_bisection": bis.pack.phi, "offset": bis.pack.phi - phi_c,
            "resolution": found["phi_c_resolution"], "seconds": time.perf_counter() - t0,
            "unjammed_at": unjammed_at,
            "stabilise_seconds": spent["stabilise"], "cycle_seconds": spent["cycle"],
            "states": rows}


def run(args, dphis, plan):
    with open(args.out, "a") as fh:
        for n, seed, m in plan:
            t = time.time()
            rec = member(args.dim, n, seed, m, dphis, args.alpha)
            rec["mode"] = args.mode
            fh.write(json.dumps(rec) + "\n")
            fh.flush()
            print(f"d={args.dim} N={n} seed={seed} member={m}: {time.time() - t:.1f} s, "
                  f"offset {rec['offset']:.2e}, resolution {rec['resolution']:.1e}, "
                  f"stabilise {rec['stabilise_seconds']:.1f} s "
                  f"(cycles {rec['cycle_seconds']:.1f} s)",
                  flush=True)
            for s in rec["states"]:
                print(f"  {s['state']}: found neg {s.get('negative_curvatures_found')} excess "
                      f"{s.get('excess_found')} -> stable {s.get('stable')} excess {s['excess']} "
                      f"escapes {s.get('escapes')} cycles {s.get('cycles')} dphi_virial "
                      f"{s['dphi_virial']:.3e}", flush=True)


def report(paths, img):
    recs = [json.loads(line) for p in paths for line in open(p) if line.strip()]
    pd = [r for r in recs if r.get("mode", "pdphi" if len(r["states"]) > 6 else "") == "pdphi"]
    cs = [r for r in recs if r not in pd]
    if pd:
        print("### p / dphi against dphi (ensemble mean +- spread over members; relative to "
              "its dphi = 1e-6 value)\n")
        keys = sorted({(r["d"], r["n"], r["alpha"]) for r in pd})
        dph = sorted({s["dphi_label"] for r in pd for s in r["states"][1:]})
        print("| d | N | alpha | members | " + " | ".join(f"{x:.0e}" for x in dph) + " |")
        print("|---" * (4 + len(dph)) + "|")
        for d, n, a in keys:
            group = [r for r in pd if (r["d"], r["n"], r["alpha"]) == (d, n, a)]
            cells = []
            for x in dph:
                rel = []
                for r in group:
                    ref = [s for s in r["states"] if s["dphi_label"] == 1e-6][0]
                    c6 = ref["p"] / 1e-6 ** (a - 1)
                    s = [s for s in r["states"] if s["dphi_label"] == x]
                    if s:  # else the ladder unjammed before this step
                        rel.append(s[0]["p"] / x ** (a - 1) / c6 - 1.0)
                rel = np.array(rel)
                lost = len(group) - len(rel)
                cells.append((f"{100 * rel.mean():+.2f}% ({100 * np.abs(rel).max():.2f})"
                              if len(rel) else "") + (f" [{lost} unjammed]" if lost else ""))
            print(f"| {d} | {n} | {a:g} | {len(group)} | " + " | ".join(cells) + " |")
        print("\nCells: mean of p/dphi^(alpha-1) relative to its value at 1e-6, in %, and in "
              "brackets the largest deviation of a member.\n")
        print("| d | N | alpha | members | bisection offset (mean) | old label error at 1e-8 | "
              "resolution of phi_c (max) | unstable states (found -> after) | compression "
              "cycles | virial dphi off its label (flagged) | s / member |")
        print("|---|---|---|---|---|---|---|---|---|---|---|")
        for d, n, a in keys:
            group = [r for r in pd if (r["d"], r["n"], r["alpha"]) == (d, n, a)]
            off = np.mean([r["offset"] for r in group])
            res = max(r["resolution"] for r in group)
            found = sum(s.get("negative_curvatures_found", 0) > 0 or s.get("excess_found", 0) < 0
                        for r in group for s in r["states"])
            after = sum(not s.get("stable", 1) for r in group for s in r["states"])
            sec = np.mean([r["seconds"] for r in group])
            cyc = sum(s.get("cycles", 0) for r in group for s in r["states"])
            off_label = [f"seed {r['seed']} {s['dphi_label']:.0e}: {s['dphi_virial']:.2e}"
                         for r in group for s in r["states"][1:] if virial_off(s)]
            print(f"| {d} | {n} | {a:g} | {len(group)} | {off:.2e} | x{1 + off / 1e-8:.1f} "
                  f"| {res:.1e} "
                  f"| {found} -> {after} | {cyc} | {'; '.join(off_label) or 'none'} "
                  f"| {sec:.0f} |")
        if img:
            plot(pd, img)
    if cs:
        print("\n### Stability census\n")
        print("| d | N | dphi | members | negative curvature found | Nc < Nc_iso found | "
              "unstable after | Nc - Nc_iso after (min..max) | escapes (total) | "
              "compression cycles (total) | virial dphi off its label |")
        print("|---|---|---|---|---|---|---|---|---|---|---|")
        keys = sorted({(r["d"], r["n"]) for r in cs})
        for d, n in keys:
            group = [r for r in cs if (r["d"], r["n"]) == (d, n)]
            for x in sorted({s["dphi_label"] for r in group for s in r["states"][1:]}):
                ss = [s for r in group for s in r["states"] if s["dphi_label"] == x]
                ex = [s["excess"] for s in ss]
                print(f"| {d} | {n} | {x:.0e} | {len(ss)} | "
                      f"{sum(s['negative_curvatures_found'] > 0 for s in ss)} | "
                      f"{sum(s['excess_found'] < 0 for s in ss)} | "
                      f"{sum(not s['stable'] for s in ss)} | {min(ex)}..{max(ex)} | "
                      f"{sum(s['escapes'] for s in ss)} | {sum(s.get('cycles', 0) for s in ss)} "
                      f"| {sum(virial_off(s) for s in ss)} |")
            tot = np.array([r["seconds"] for r in group])
            stab = np.array([r["stabilise_seconds"] for r in group])
            cyc = np.array([r.get("cycle_seconds", 0.0) for r in group])
            print(f"\nd = {d}, N = {n}: {np.mean(tot):.1f} s per member in all, of which "
                  f"{np.mean(stab):.2f} s ({100 * np.sum(stab) / np.sum(tot):.1f} %) in the "
                  f"stability checks and escapes (max {np.max(stab):.2f} s), compression "
                  f"cycles {np.sum(cyc):.1f} s in all (max {np.max(cyc):.1f} s per member)\n")
            print("| member | " + " | ".join(f"Nc - Nc_iso found -> after at {x:.0e}" for x in
                                               sorted({s["dphi_label"] for r in group
                                                       for s in r["states"][1:]}))
                  + " | check + escapes + cycles (s) | member (s) |")
            print("|---" * (3 + len(group[0]["states"][1:])) + "|")
            for r in sorted(group, key=lambda r: r["member"]):
                cells = [f"{s['excess_found']} -> {s['excess']}"
                         + ("" if s["stable"] else " UNSTABLE")
                         + (f" ({s['cycles']} cycle(s))" if s.get("cycles") else "")
                         for s in sorted(r["states"][1:], key=lambda s: s["dphi_label"])]
                print(f"| {r['member']} | " + " | ".join(cells)
                      + f" | {r['stabilise_seconds']:.1f} | {r['seconds']:.0f} |")


def virial_off(s):
    """The state's own virial dphi disagrees with its label (parjam.pack.ensemble.virial_flags)."""
    from parjam.pack.ensemble import virial_tolerance

    x, v = s["dphi_label"], s.get("dphi_virial", np.nan)
    return bool(np.isfinite(v) and abs(v - x) > virial_tolerance(x) * x)


def census_files(paths):
    """Census table (stability found -> after, Nc - Nc_iso) from written packing files."""
    import h5py

    from parjam.files import h5md

    rows = {}
    for path in paths:
        with h5py.File(path, "r") as f:
            o, par = f["observables"], f["parameters"].attrs
            state = par["state"]
            state = state.decode() if isinstance(state, bytes) else str(state)
            rows.setdefault(state, []).append({k: h5md.observable(f, k) for k in (
                "excess", "stable", "negative_curvatures_found", "excess_found", "escapes",
                "cycles", "dphi_virial_ok", "max_force_rel", "pressure", "N_active") if k in o} | {
                    "member": int(par["member"]), "seconds": float(par["seconds"])})
    print("| state | members | negative curvature found | Nc < Nc_iso found | unstable after "
          "| Nc - Nc_iso after (min..max) | escapes (total) | compression cycles (total) "
          "| virial dphi off its label |")
    print("|---|---|---|---|---|---|---|---|---|")
    for state in sorted(rows, key=lambda s: (s != "phi_c", float(s[4:]) if s != "phi_c" else 0)):
        ss = rows[state]
        print(f"| {state} | {len(ss)} | {sum(s['negative_curvatures_found'] > 0 for s in ss)} | "
              f"{sum(s['excess_found'] < 0 for s in ss)} | {sum(not s['stable'] for s in ss)} | "
              f"{min(s['excess'] for s in ss)}..{max(s['excess'] for s in ss)} | "
              f"{sum(s['escapes'] for s in ss)} | {sum(s.get('cycles', 0) for s in ss)} | "
              f"{sum(not s.get('dphi_virial_ok', 1) for s in ss)} |")
    seconds = {}
    for ss in rows.values():
        for r in ss:
            seconds[r["member"]] = max(seconds.get(r["member"], 0.0), r["seconds"])
    print(f"\nmembers {sorted(seconds)}; seconds per member (the largest 'seconds' of its "
          f"files): " + ", ".join(f"{seconds[m]:.0f}" for m in sorted(seconds)))
    # Eq. (22): dz = C0 p^b over dphi = 1e-5 .. 1e-1, least squares in log-log of the ensemble
    # means, dz = 2 (Nc - Nc_iso) / N' (docs/results/reproduction.md conventions)
    fit = [st for st in rows if st != "phi_c" and 1e-5 <= float(st[4:]) <= 1e-1]
    if fit:
        members = sorted({r["member"] for st in fit for r in rows[st]})
        p = np.array([np.mean([r["pressure"] for r in rows[st]]) for st in fit])
        dz = np.array([np.mean([2.0 * r["excess"] / r["N_active"] for r in rows[st]])
                       for st in fit])
        b, lnc = np.polyfit(np.log(p), np.log(dz), 1)
        print(f"\nEq. (22) over {len(fit)} states, members {members} (all {len(members)}): "
              f"dz = {np.exp(lnc):.2f} p^{b:.3f}")


def plot(recs, img):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    keys = sorted({(r["d"], r["n"], r["alpha"]) for r in recs})
    flagged = False
    for k, key in enumerate(keys):
        group = [r for r in recs if (r["d"], r["n"], r["alpha"]) == key]
        for j, r in enumerate(group):
            st = [s for s in r["states"][1:]]
            x = np.array([s["dphi_label"] for s in st])
            y = np.array([s["p"] / s["dphi_label"] ** (key[2] - 1) for s in st])
            name = f"d={key[0]} N={key[1]}" + (f" alpha={key[2]:g}" if key[2] != 2 else "")
            ax.loglog(x, y, "o-" if key[0] == 3 else "s--", color=f"C{k}", ms=3, lw=0.8,
                      label=name if j == 0 else None)
            off = np.array([virial_off(s) for s in st], dtype=bool)
            ax.loglog(x[off], y[off], "kx", ms=6,
                      label="virial dphi off its label (flagged)" if off.any() and not flagged
                      else None)
            flagged = flagged or off.any()
    ax.set(xlabel=r"$\Delta\phi$", ylabel=r"$p / \Delta\phi^{\alpha-1}$",
           title="pressure over distance to the refined $\\phi_c$")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(img, dpi=90)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mode", choices=("pdphi", "census", "report", "files"))
    ap.add_argument("files", nargs="*")
    ap.add_argument("--dim", type=int, default=3)
    ap.add_argument("--n", type=int, nargs="+", default=[64])
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--members", type=int, default=20)
    ap.add_argument("--member-list", type=int, nargs="+",
                    help="census: only these members (e.g. the ones an earlier census flagged)")
    ap.add_argument("--alpha", type=float, default=2.0)
    ap.add_argument("--dphi", type=float, nargs="+")
    ap.add_argument("--out", default="bench-out/extremes.jsonl")
    ap.add_argument("--img")
    args = ap.parse_args()
    if args.mode == "report":
        report(args.files, args.img)
        return 0
    if args.mode == "files":
        census_files(args.files)
        return 0
    from parjam import env

    env.init()
    if args.mode == "pdphi":
        dphis = args.dphi or [10.0 ** -k for k in range(10, 0, -1)]
        seeds = args.member_list or range(args.seeds)  # pdphi: --member-list picks seeds
        plan = [(n, seed, 0) for n in args.n for seed in seeds]
    else:
        dphis = args.dphi or [1e-9, 1e-8, 1e-6]
        members = args.member_list or range(args.members)
        plan = [(n, 2005, m) for n in args.n for m in members]
    run(args, dphis, plan)
    return 0


if __name__ == "__main__":
    sys.exit(main())
