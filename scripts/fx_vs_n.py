"""The overlap function f(x) of the soft modes against N (docs/results/reproduction.md section 12):
isostatic members at several N, both cut geometries, one results JSON.

Why one file of ~510 lines: run, adopt, collect and tables share one directory layout
(ROOT/N{N}[_s{seed}]/packings, cuts, costs.json) and one JSON schema; split, each would have to
restate them.

    python scripts/fx_vs_n.py run --n 1024 4096 --members 5 --root DIR [--launch "srun"]
    python scripts/fx_vs_n.py adopt --n N --packings OUT --log LOG --root DIR   (optional)
    python scripts/fx_vs_n.py collect --root DIR --out results.json
    python scripts/fx_vs_n.py tables results.json      # the tables of reproduction.md sec. 12
    parjam plot results.json --out docs/img/fx_vs_n.png

``run``, for each N (3D, monodisperse, harmonic):

1. packs member m = 0, 1, 2, ... of seed S (default S = N) one at a time:
   ``parjam pack --dim 3 --n N --dphi DPHI --phic-method extrapolate --seed S --members m+1``
   into DIR/N{N}/packings (the members already there are skipped by pack's resume), measuring
   the wall time and peak RSS of that member (/usr/bin/time on every rank);
2. counts Nc - Nc_iso of the non-rattlers (parjam.softmodes.prepare); a member with
   Nc != Nc_iso is kept on disk and recorded but not cut; it stops when --members isostatic
   members exist or after --max-tries members;
3. cuts every isostatic member twice with ``parjam softmodes``: one plane (``--cut x=0.5``,
   e0 = 0.1) and all faces of the cube (``--subdivide 1``, the planes x = y = z = 0, e0 = 0.05,
   since a uniform mode has e = 1/8 there), into DIR/N{N}/cuts/.

Every step is skipped when its output exists (a rerun resumes); costs go to
DIR/N{N}/costs.json.  ``collect`` reads every cut file (never recomputes) and writes per member:
f(x), c, q'/q on the e0 ladder, mean extension, omega_t^2, mean modulated energy, costs; per N
and geometry: means with bootstrap errors over members (parjam.study.fits); and the fits against L
(trial energies ~ L^b, c ~ L^b), with the variational bound q'/q >= (c/2 - e0)/(1 - e0)
evaluated (section 12 of docs/results/reproduction.md says what each number means).
"""

import argparse
import glob
import json
import os
import re
import shlex
import subprocess
import sys
import time

import h5py
import numpy as np

from parjam import env, softmodes as sm
from parjam.files import h5md
from parjam.study import fits

def mpirun():
    """$PARJAM_MPIRUN split (scripts/mpi-env), else an oversubscribing mpirun."""
    return shlex.split(os.environ.get("PARJAM_MPIRUN", "mpirun --oversubscribe"))

GEOMETRIES = {  # name: (parjam softmodes arguments, e0 of its trial modes)
    "plane": (["--cut", "x=0.5"], 0.1),
    "faces": (["--subdivide", "1"], 0.05),
}
E0_REPORT = (0.05, 0.1, 0.2)


def parjam_argv():
    return [sys.executable, "-m", "parjam"]


def member_file(packdir, m):
    found = sorted(glob.glob(os.path.join(packdir, f"member{m:04d}_dphi*.h5")))
    return found[0] if found else None


def excess_of(path):
    """Nc - Nc_iso of the non-rattlers of a packing (serial)."""
    env.init()
    pack = h5md.read_packing(path)
    cs = sm.prepare(pack, [sm.Plane(0, 0.5)], allow_hyperstatic=True)
    return int(cs.excess), int(cs.n)


def load(path, default):
    if os.path.exists(path):
        with open(path) as fh:
            return json.load(fh)
    return default


def save(path, obj):
    tmp = path + ".tmp"
    with open(tmp, "w") as fh:
        json.dump(obj, fh, indent=1)
    os.replace(tmp, path)


def dphi_for(n, dphi):
    """The packing's dphi: a number as given, or ``"auto"``: 1e-8 up to N = 4096 and
    1e-8 (4096 / N)^2 above.  Why: the expected number of excess contacts after rattler removal
    is Nc - Nc_iso = N' dz_iso / 2 with dz_iso ~ p^(1/2) ~ dphi^(1/2) (Eq. 22), i.e. it grows as
    N dphi^(1/2): at a fixed dphi an exactly isostatic member gets rarer as N grows (at 1e-8
    the measured census is 5 of 5 at N = 1024 and about 1 in 3 at 4096; at 16384 Eq. 22 gives
    ~6 excess contacts), and keeping N dphi^(1/2) at its N = 4096 value keeps the census of
    4096 (docs/results/reproduction.md section 12)."""
    if dphi != "auto":
        return float(dphi)
    return 1e-8 * min(1.0, (4096.0 / n) ** 2)


def dphi_arg(text):
    if text == "auto":
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--dphi takes a number or 'auto', got {text!r}")


def size_dir(root, n, seed):
    """ROOT/N{N} for the default seed N, ROOT/N{N}_s{seed} for another series of the same N."""
    return os.path.join(root, f"N{n}" if seed in (None, n) else f"N{n}_s{seed}")


def run_size(n, args):
    base = size_dir(args.root, n, args.seed)
    packdir, cutdir = os.path.join(base, "packings"), os.path.join(base, "cuts")
    os.makedirs(cutdir, exist_ok=True)
    costs_path = os.path.join(base, "costs.json")
    costs = load(costs_path, {"N": n, "seed": args.seed or n, "dphi": dphi_for(n, args.dphi),
                              "members": {}})
    seed, dphi = costs["seed"], costs["dphi"]
    if dphi != dphi_for(n, args.dphi):
        raise SystemExit(f"{base} was started at dphi = {dphi:g}, not {dphi_for(n, args.dphi):g}: "
                         "give that --dphi, or another --seed or --root")
    launch = shlex.split(args.launch) if args.launch else []
    ranks = args.ranks
    iso = 0
    for m in range(args.max_tries):
        if iso >= args.members:
            break
        rec = costs["members"].setdefault(str(m), {})
        if member_file(packdir, m) is None:
            argv = parjam_argv() + ["pack", "--dim", "3", "--n", str(n), "--dphi", str(dphi),
                                    "--phic-method", "extrapolate", "--seed", str(seed),
                                    "--members", str(m + 1), "--no-phic-file", "-q",
                                    "--out", packdir]
            mb, secs, cpu, res = run_measured(ranks, argv, launch)
            if res.returncode != 0 or member_file(packdir, m) is None:
                raise SystemExit(f"pack N = {n} member {m} failed: {res.stderr[-500:]}")
            rec["pack"] = {"seconds": secs, "cpu_seconds": cpu, "peak_mb_per_rank": max(mb),
                           "ranks": ranks}
        if "excess" not in rec:
            rec["excess"], rec["N_active"] = excess_of(member_file(packdir, m))
        save(costs_path, costs)
        print(f"N = {n} member {m}: Nc - Nc_iso = {rec['excess']:+d}", flush=True)
        if rec["excess"] != 0:
            continue
        iso += 1
        for geo, (extra, e0) in GEOMETRIES.items():
            out = os.path.join(cutdir, f"m{m}_{geo}.h5")
            if os.path.exists(out):
                continue
            argv = parjam_argv() + ["softmodes", member_file(packdir, m), *extra,
                                    "--e0", str(e0), "--bins", str(args.bins), "-q",
                                    "--out", out]
            if args.scratch:
                argv += ["--scratch", args.scratch]
            mb, secs, cpu, res = run_measured(ranks, argv, launch)
            if res.returncode != 0:
                raise SystemExit(f"softmodes N = {n} member {m} {geo}: {res.stderr[-500:]}")
            rec[geo] = {"seconds": secs, "cpu_seconds": cpu, "peak_mb_per_rank": max(mb),
                        "ranks": ranks}
            save(costs_path, costs)
    print(f"N = {n}: {iso} isostatic member(s) of {len(costs['members'])} packed", flush=True)


def adopt(args):
    """Take over members packed by one ``parjam pack --members M`` process (its --out DIR moved
    to ROOT/N{N}/packings, seed N) and their per-member costs from its progress log: a member's
    time is from the previous member's last line to its own last one; the peak RSS is the
    whole process's (/usr/bin/time -v), an upper bound for each member; its CPU time is the
    process's, times the fraction of its wall time the adopted members took, shared evenly."""
    base = size_dir(args.root, args.n, args.seed)
    packdir = os.path.join(base, "packings")
    if os.path.exists(packdir):
        raise SystemExit(f"{packdir} exists")
    os.makedirs(base, exist_ok=True)
    os.replace(args.packings, packdir)
    text = open(args.log).read()
    last = {}
    for t, m in re.findall(r"\[\s*([0-9.]+) s\] member (\d+) of", text):
        last[int(m)] = float(t)
    peak = re.search(r"Maximum resident set size \(kbytes\): (\d+)", text)
    peak_mb = int(peak.group(1)) / 1024.0 if peak else None
    cpu = [float(x) for x in re.findall(r"(?:User|System) time \(seconds\): ([0-9.]+)", text)]
    costs = {"N": args.n, "seed": args.seed or args.n, "dphi": args.dphi, "members": {}}
    prev = 0.0
    for m in sorted(last):
        if member_file(packdir, m) is None:
            break
        costs["members"][str(m)] = {"pack": {"seconds": last[m] - prev, "peak_mb_per_rank": peak_mb,
                                             "ranks": 1, "from": "log of one --members process"}}
        prev = last[m]
    # the process's CPU time shared evenly over the adopted members, in proportion to the wall
    # time they took of the whole process (it may have been stopped inside a further member)
    wall = re.search(r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): ([0-9:.]+)", text)
    total = sum(float(x) * 60 ** k for k, x in enumerate(reversed(wall.group(1).split(":")))) \
        if wall else None
    for rec in costs["members"].values():
        rec["pack"]["cpu_seconds"] = (sum(cpu) * min(prev / total, 1.0) / len(costs["members"])
                                      if cpu and total else None)
    save(os.path.join(base, "costs.json"), costs)
    print(f"adopted {len(costs['members'])} member(s) of N = {args.n}")


def run_measured(ranks, argv, launch):
    """Run ``argv`` on ``ranks`` ranks ($PARJAM_MPIRUN) or under an explicit
    launcher (HPC: srun), one thread per rank: (peak RSS per rank in MB, wall seconds, CPU
    seconds summed over the ranks, CompletedProcess).  The CPU time is the cost to quote on a
    shared machine, where the wall time depends on the load."""
    cmd = (launch or mpirun() + ["-n", str(ranks)]) + [
        "/usr/bin/time", "-f", "PEAKRSS %M CPU %U %S"] + list(argv)
    t0 = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True,
                         env=dict(os.environ, OMP_NUM_THREADS="1"))
    secs = time.perf_counter() - t0
    found = re.findall(r"PEAKRSS (\d+) CPU ([0-9.]+) ([0-9.]+)", res.stderr)
    mb = [int(m) / 1024.0 for m, _, _ in found] or [float("nan")]
    cpu = sum(float(u) + float(s) for _, u, s in found) if found else float("nan")
    return mb, secs, cpu, res


# ----------------------------------------------------------------------------- collect

def read_cut(path):
    with h5py.File(path, "r") as f:
        g = f["softmodes"]
        cnt, te = g["count"].attrs, g["trial_energy"].attrs
        ext = g["extension"][()]
        q, n_basis = int(cnt["q"]), int(cnt["n_basis"])
        fr = g["extended_fraction"][()]
        return {
            "x": g["overlap"][:, 0].tolist(), "f": g["overlap"][:, 1].tolist(),
            "f_nontrivial": g["overlap"][:, 2].tolist(),
            "c": float(g["overlap"].attrs["c"]),
            "c_nontrivial": float(g["overlap"].attrs["c_nontrivial"]),
            "q": q, "n_soft": n_basis, "count": int(g["count"][()]),
            "localised": int(cnt["localised"]), "excess": int(cnt["excess"]),
            "N_active": int(cnt["N_active"]),
            "mean_e": float(np.mean(ext)),
            "q_prime_over_q": {f"{e0:g}": float(np.count_nonzero(ext > e0) / q)
                               for e0 in E0_REPORT},
            "ladder": fr.tolist(),
            "e0": float(te["e0"]), "omega_t2": float(te["omega_t2"]),
            "omega_L2": float(te["omega_L2"]), "q_prime": int(te["q_prime"]),
            "n_below_2omega_t2": int(te["n_below_2omega_t2"]),
            "mean_modulated_energy": float(te["mean_modulated_energy"]),
            "seconds": {k: float(g.attrs[k]) for k in ("seconds_count", "seconds_null_space",
                                                       "seconds_analysis")},
            "peak_rss_mb": float(g.attrs["peak_rss_mb"]),
        }


def box_edge(path):
    return float(h5md.read_packing(path).L)


def mean_err(values, n_boot=2000, seed=0):
    """Mean over members and its bootstrap error (parjam.study.fits.bootstrap)."""
    v = np.asarray(values, float)
    if len(v) < 2:
        return np.mean(v, axis=0).tolist(), np.full(np.shape(v)[1:], np.nan).tolist()
    best, boots = fits.bootstrap(lambda rows: np.mean(v[rows], axis=0), len(v), n_boot, seed)
    return best.tolist(), np.std(boots, axis=0).tolist()


def cost_summary(records, what):
    """Mean wall and CPU seconds and the largest peak RSS per rank of some measured commands."""
    def mean(key):
        vals = [r[key] for r in records if r.get(key) is not None and np.isfinite(r[key])]
        return float(np.mean(vals)) if vals else None

    peaks = [r["peak_mb_per_rank"] for r in records if r.get("peak_mb_per_rank") is not None]
    return {f"{what}_seconds": mean("seconds"), f"{what}_cpu_seconds": mean("cpu_seconds"),
            f"{what}_peak_mb": float(np.max(peaks)) if peaks else None,
            f"{what}_timed": len(records)}


def bound(c_like, e0):
    """The paper's variational bound q'/q >= (c/2 - e0)/(1 - e0) written with the mean
    extension: q'/q >= (n_soft/q) (e_mean - e0)/(1 - e0) (each e <= max g^2 = 1)."""
    return (c_like - e0) / (1.0 - e0)


def collect(args):
    members, summary = [], {}
    series = [(load(os.path.join(b, "costs.json"), None), b)
              for b in sorted(glob.glob(os.path.join(args.root, "N*")))]
    series = sorted(((c, b) for c, b in series if c is not None),
                    key=lambda cb: (int(cb[0]["N"]), int(cb[0]["seed"])))
    for costs, base in series:
        n = int(costs["N"])
        packdir = os.path.join(base, "packings")
        for m, rec in sorted(costs["members"].items(), key=lambda kv: int(kv[0])):
            row = {"N": n, "seed": costs["seed"], "dphi": costs.get("dphi"), "member": int(m),
                   "excess": rec.get("excess"),
                   "pack": rec.get("pack"), "cuts": {}}
            path = member_file(packdir, int(m))
            row["L"] = box_edge(path) if path else None
            for geo in GEOMETRIES:
                cut = os.path.join(base, "cuts", f"m{m}_{geo}.h5")
                if os.path.exists(cut):
                    row["cuts"][geo] = read_cut(cut)
                    row["cuts"][geo]["cost"] = rec.get(geo)
            members.append(row)
    sizes = sorted({r["N"] for r in members})
    for geo, (_, e0_run) in GEOMETRIES.items():
        per_n = {}
        for n in sizes:
            rows = [r for r in members if r["N"] == n and geo in r["cuts"]]
            if not rows:
                continue
            cuts = [r["cuts"][geo] for r in rows]
            s = {"members": len(rows), "L": float(np.mean([r["L"] for r in rows])),
                 "x": cuts[0]["x"]}
            for key in ("c", "c_nontrivial", "mean_e", "omega_t2", "mean_modulated_energy",
                        "n_soft", "q", "localised"):
                s[key], s[key + "_err"] = mean_err([c[key] for c in cuts])
            s["f"], s["f_err"] = mean_err([c["f"] for c in cuts])
            s["f_nontrivial"], s["f_nontrivial_err"] = mean_err([c["f_nontrivial"] for c in cuts])
            for e0 in E0_REPORT:
                key = f"{e0:g}"
                s[f"qpq_{key}"], s[f"qpq_{key}_err"] = mean_err([c["q_prime_over_q"][key]
                                                                 for c in cuts])
                ratio = float(np.mean([c["n_soft"] / c["q"] for c in cuts]))
                # the paper's form, c/2 for one plane (g = sin(pi x/L), mean sin^2 = 1/2); for
                # the cube the analogue c/8 needs the 3D density >= c (only f(x) is measured)
                cg = s["c"] * (0.5 if geo == "plane" else 0.125)
                s[f"bound_c_{key}"] = ratio * bound(cg, e0)
                s[f"bound_mean_e_{key}"] = ratio * bound(s["mean_e"], e0)
            # the variational count: eigenmodes of the uncut M below 2 omega_t^2 against q'/2
            s["variational_ok"] = sum(c["n_below_2omega_t2"] >= 0.5 * c["q_prime"] for c in cuts)
            s["n_below_over_half_qprime"] = float(np.min(
                [c["n_below_2omega_t2"] / (0.5 * c["q_prime"]) for c in cuts]))
            s.update(cost_summary([c["cost"] for c in cuts if c.get("cost")], "cut"))
            s["cut_solver_seconds"] = float(np.mean([sum(c["seconds"].values()) for c in cuts]))
            s["cut_solver_peak_mb"] = float(np.max([c["peak_rss_mb"] for c in cuts]))
            per_n[str(n)] = s
        fit = {}
        if len(per_n) >= 2:
            ns = [int(k) for k in per_n]
            width = max(per_n[str(n)]["members"] for n in ns)
            L = np.array([[per_n[str(n)]["L"] for n in ns]])
            for key in ("omega_t2", "mean_modulated_energy", "c", "c_nontrivial"):
                table = np.full((width, len(ns)), np.nan)
                for j, n in enumerate(ns):
                    vals = [r["cuts"][geo][key] for r in members
                            if r["N"] == n and geo in r["cuts"]]
                    table[:len(vals), j] = vals
                fit[key] = fits.fit_power(L, table)
        summary[geo] = {"e0_run": e0_run, "per_N": per_n, "fit_against_L": fit}
    packs = {}
    for n in sizes:
        rows = [r for r in members if r["N"] == n and r["excess"] is not None]  # checked
        packs[str(n)] = {
            "tried": len(rows), "isostatic": sum(r["excess"] == 0 for r in rows),
            "excess": [r["excess"] for r in rows],
            "dphi": [r["dphi"] for r in rows],
            **cost_summary([r["pack"] for r in rows if r.get("pack")], "pack")}
    out = {"format": "parjam-fx-vs-n", "root": os.path.abspath(args.root),
           "geometries": {k: {"args": v[0], "e0": v[1]} for k, v in GEOMETRIES.items()},
           "packs": packs, "summary": summary, "members": members}
    save(args.out, out)
    print(f"wrote {args.out}: {len(members)} members, N = {sizes}")


def fmt_or_dash(v, fmt):
    return "-" if v is None else fmt.format(v)


def pm(v, e, fmt="{:.3f}"):
    return fmt.format(v) + ("" if e is None or not np.isfinite(e) else " +- " + fmt.format(e))


def tables(args):
    """The markdown tables of docs/results/reproduction.md section 12, from the results JSON."""
    res = load(args.results, None)
    lines = ["| N | packed (checked) | isostatic | Nc - Nc_iso (dphi) | pack CPU s / wall s per "
             "member | pack peak MB |", "|---|---|---|---|---|---|"]
    for n, p in sorted(res["packs"].items(), key=lambda kv: int(kv[0])):
        cpu, wall, peak = (p.get(f"pack_{k}") for k in ("cpu_seconds", "seconds", "peak_mb"))
        dphis = p.get("dphi") or [None] * len(p["excess"])
        census = "; ".join(", ".join(f"{x:+d}" for x, y in zip(p["excess"], dphis) if y == dp)
                           + ("" if dp is None else f" ({dp:g})")
                           for dp in sorted(set(dphis), key=lambda v: -(v or 0)))
        lines.append(f"| {n} | {p['tried']} | {p['isostatic']} | {census}"
                     f" | {fmt_or_dash(cpu, '{:.1f}')} / {fmt_or_dash(wall, '{:.0f}')} | "
                     f"{fmt_or_dash(peak, '{:.0f}')} |")
    print("\n".join(lines) + "\n")
    for geo, g in res["summary"].items():
        print(f"{geo} (e0 of the trial modes {g['e0_run']:g})\n")
        print("| N | members | L | c | c, localised out | q'/q e0 = 0.05 | q'/q e0 = 0.1 | "
              "q'/q e0 = 0.2 | mean e | bound (mean e) 0.1 / 0.2 | bound (c) 0.1 / 0.2 | "
              "omega_t^2 | <g dR|M|g dR> | cut CPU s | solver wall s | peak MB |")
        print("|" + "---|" * 16)
        for n, s in sorted(g["per_N"].items(), key=lambda kv: int(kv[0])):
            print(f"| {n} | {s['members']} | {s['L']:.2f} | {pm(s['c'], s['c_err'])} | "
                  f"{pm(s['c_nontrivial'], s['c_nontrivial_err'])} | "
                  + " | ".join(pm(s[f'qpq_{e}'], s[f'qpq_{e}_err']) for e in ("0.05", "0.1", "0.2"))
                  + f" | {s['mean_e']:.3f} | {s['bound_mean_e_0.1']:.3f} / "
                  f"{s['bound_mean_e_0.2']:.3f} | {s['bound_c_0.1']:.3f} / "
                  f"{s['bound_c_0.2']:.3f} | "
                  f"{pm(s['omega_t2'], s['omega_t2_err'], '{:.4f}')} | "
                  f"{pm(s['mean_modulated_energy'], s['mean_modulated_energy_err'], '{:.4f}')} | "
                  f"{fmt_or_dash(s['cut_cpu_seconds'], '{:.1f}')} | "
                  f"{s['cut_solver_seconds']:.2f} | {fmt_or_dash(s['cut_peak_mb'], '{:.0f}')} |")
        print()
        for key, f in g["fit_against_L"].items():
            print(f"- {key} ~ L^({f['exponent']:.3f} +- {f['exponent_err']:.3f})")
        print()
        for n, s in sorted(g["per_N"].items(), key=lambda kv: int(kv[0])):
            print(f"- f(x), N = {n}: " + " ".join(f"{v:.2f}" for v in s["f"])
                  + f"; variational count met in {s['variational_ok']} of {s['members']} "
                  f"(smallest count / (q'/2): {s['n_below_over_half_qprime']:.1f})")
        print()
    print("\n".join(cost_lines(res)))


def extrapolate(ns, values, targets):
    """Power law through the two largest sizes: (exponent, value at each target N)."""
    (n1, v1), (n2, v2) = sorted(zip(ns, values))[-2:]
    b = np.log(v2 / v1) / np.log(n2 / n1)
    return float(b), [float(v2 * (t / n2) ** b) for t in targets]


def cost_lines(res, targets=(16384, 65536)):
    """Measured per-member costs and their extrapolation to ``targets`` (markdown lines)."""
    rows = [("pack", "CPU s", {n: p.get("pack_cpu_seconds") for n, p in res["packs"].items()}),
            ("pack", "peak MB", {n: p.get("pack_peak_mb") for n, p in res["packs"].items()})]
    for geo, g in res["summary"].items():
        per = g["per_N"]
        rows += [(f"cut {geo}", "CPU s", {n: s.get("cut_cpu_seconds") for n, s in per.items()}),
                 (f"cut {geo}", "solver wall s", {n: s.get("cut_solver_seconds")
                                                  for n, s in per.items()}),
                 (f"cut {geo}", "peak MB", {n: s.get("cut_peak_mb") for n, s in per.items()}),
                 (f"cut {geo}", "n_soft", {n: s.get("n_soft") for n, s in per.items()})]
    ns_all = sorted({int(n) for _, _, v in rows for n in v})
    out = ["| stage | quantity | " + " | ".join(f"N = {n}" for n in ns_all)
           + " | exponent (two largest N) | "
           + " | ".join(f"N = {t} (extrapolated)" for t in targets)
           + " |", "|" + "---|" * (3 + len(ns_all) + len(targets))]
    for stage, what, vals in rows:
        known = {int(n): v for n, v in vals.items() if v is not None and np.isfinite(v)}
        cells = [fmt_or_dash(known.get(n), "{:.3g}") for n in ns_all]
        if len(known) >= 2:
            b, pred = extrapolate(list(known), list(known.values()), targets)
            tail = [f"{b:.2f}"] + [f"{v:.3g}" for v in pred]
        else:
            tail = ["-"] * (1 + len(targets))
        out.append(f"| {stage} | {what} | " + " | ".join(cells + tail) + " |")
        if what == "n_soft" and len(known) >= 2:  # the basis in memory, 8 N d n_soft bytes
            cells = [fmt_or_dash(None if n not in known else 24e-6 * n * known[n], "{:.3g}")
                     for n in ns_all]
            out.append(f"| {stage} | basis MB (8 x 3N x n_soft) | " + " | ".join(cells) + " | "
                       f"{b + 1:.2f} | " + " | ".join(f"{24e-6 * t * v:.3g}"
                                                      for t, v in zip(targets, pred)) + " |")
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="pack isostatic members and cut them (resumable)")
    r.add_argument("--n", type=int, nargs="+", required=True)
    r.add_argument("--members", type=int, default=5, help="isostatic members per N (5)")
    r.add_argument("--max-tries", type=int, default=12, help="members packed at most (12)")
    r.add_argument("--dphi", type=dphi_arg, default="auto",
                   help="a number, or auto: 1e-8 up to N = 4096, 1e-8 (4096/N)^2 above (auto)")
    r.add_argument("--seed", type=int, help="ensemble seed (default: N)")
    r.add_argument("--bins", type=int, default=10)
    r.add_argument("--ranks", type=int, default=1, help="MPI ranks per command (1)")
    r.add_argument("--launch", default="", help="launcher replacing mpirun (e.g. 'srun -n 64')")
    r.add_argument("--scratch", help="parjam softmodes --scratch DIR (basis out of core)")
    r.add_argument("--root", required=True)
    a = sub.add_parser("adopt", help="take over the members of one parjam pack --members run")
    a.add_argument("--n", type=int, required=True)
    a.add_argument("--packings", required=True, help="that run's --out directory (moved)")
    a.add_argument("--log", required=True, help="its progress output with /usr/bin/time -v")
    a.add_argument("--seed", type=int, help="its --seed (default: N)")
    a.add_argument("--dphi", type=float, default=1e-8)
    a.add_argument("--root", required=True)
    c = sub.add_parser("collect", help="read every cut file into one results JSON")
    c.add_argument("--root", required=True)
    c.add_argument("--out", required=True)
    t = sub.add_parser("tables", help="print the markdown tables of the results JSON")
    t.add_argument("results")
    args = p.parse_args(argv)
    if args.cmd == "tables":
        tables(args)
    elif args.cmd == "adopt":
        adopt(args)
    elif args.cmd == "run":
        if args.members < 1 or args.max_tries < args.members or (
                args.dphi != "auto" and args.dphi <= 0):
            p.error("need 1 <= --members <= --max-tries and --dphi > 0")
        for n in args.n:
            run_size(n, args)
    else:
        collect(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
