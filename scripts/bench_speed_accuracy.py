#!/usr/bin/env python3
"""Speed against accuracy for every knob of parjam's spectra and packings, measured in one run
against the dense LAPACK truth (docs/speed-accuracy.md, Pareto plots docs/img/speed_*.png).

    nice -n 10 .venv/bin/python scripts/bench_speed_accuracy.py \
        --eig P1024.h5 P2048.h5 --dos P1024.h5 P2048.h5 P4096.h5 \
        --ftol-phic PC1024.h5 --json out.json --md docs/speed-accuracy.md

Stages (each one process, serial, OMP/BLAS threads = 1 for fair timings):

- ``eig``: the k lowest modes by SLEPc shift-and-invert against the dense eigenvalues, varying
  the convergence tolerance, ncv, and the factorisation package (MUMPS LDL^T on SBAIJ as parjam
  does, MUMPS LU, SuperLU_dist LU, PETSc's own Cholesky, CHOLMOD, UMFPACK); the peer
  scipy.sparse.linalg.eigsh (shift-invert, SuperLU) in the same run.  Metrics: time (EPSSolve
  including the factorisation), the largest true residual ||D v - lambda v|| / ||D||_inf and the
  largest relative eigenvalue error against dense.
- ``dos``: D(omega) of the full matrix by dense LAPACK (numpy eigvalsh of the deflated matrix;
  the truth), by spectrum slicing of the lowest 10 % (parjam ``slice``) and by KPM
  (parjam.vib.kpm) for moments x probes on a grid.  KPM costs are measured once for the largest
  moments x probes (the moments of fewer moments and of the first probes are exactly those of
  a shorter run with the same seed) and the time of each point is assembly + bounds + (its
  share of the measured moment time); two points are also timed directly to check that model.  Metrics:
  L1 distance of the per-mode D(omega) on 40 bins, relative error of D0 (same plateau window as
  dense) and absolute error of omega*.
- ``ftol``: from a converged phi_c packing, affine compression to phi_c + dphi (dphi = 1e-2 and
  1e-6) and minimisation to the residual force ftol (what ``parjam pack --ftol`` does), against
  the same with ftol = 1e-13: the residual reached, time, the errors of the 20 lowest
  eigenvalues, of dz and of p, and the number of negative eigenvalues (dense, translations
  deflated).
"""

import argparse
import json
import os
import platform
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)


def load(path):
    from parjam.files import h5md
    from parjam.vib import spectrum

    return spectrum.active_system(h5md.read_packing(path))


def dense_truth(system, cache):
    """All eigenvalues of the full matrix (translations deflated) and the time it took."""
    from parjam.vib import spectrum

    if cache and os.path.exists(cache):
        z = np.load(cache)
        return z["lam"], float(z["seconds"])
    t0 = time.perf_counter()
    H = spectrum.dense_matrix(system, "full")
    norm = float(np.abs(H).sum(axis=1).max())
    lam = np.linalg.eigvalsh(spectrum.deflated_dense(H, system.n, system.d, norm))
    seconds = time.perf_counter() - t0
    lam = lam[:system.n_modes]
    if cache:
        np.savez(cache, lam=lam, seconds=seconds)
    return lam, seconds


# --- eigensolver knobs ----------------------------------------------------------------------------
FACTORS = {  # name: (matrix type, PC type, package, extra options)
    "mumps-cholesky": ("sbaij", "cholesky", "mumps", {}),
    "mumps-lu": ("aij", "lu", "mumps", {}),
    "superlu_dist-lu": ("aij", "lu", "superlu_dist", {}),
    "petsc-cholesky": ("aij", "cholesky", "petsc", {"st_pc_factor_mat_ordering_type": "nd"}),
    "cholmod-cholesky": ("aij", "cholesky", "cholmod", {}),
    "umfpack-lu": ("aij", "lu", "umfpack", {}),
}


def run_sinvert(system, k, tol, ncv=None, factor="mumps-cholesky", mpd=None):
    from parjam import env
    from parjam.vib import spectrum, translations

    PETSc, SLEPc = env.petsc(), env.slepc()
    comm = PETSc.COMM_WORLD
    mtype, pctype, pkg, extra = FACTORS[factor]
    opts = PETSc.Options()
    values = {"st_pc_type": pctype, "st_pc_factor_mat_solver_type": pkg, **extra}
    if ncv:
        values["eps_ncv"] = str(ncv)
    if mpd:
        values["eps_mpd"] = str(mpd)
    for key, val in values.items():
        opts.setValue(spectrum.PREFIX + key, val)
    A = spectrum.dynamical_matrix(comm, system, "full")
    norm = A.norm(PETSc.NormType.INFINITY)
    defl = translations.vectors(A, system.d)
    t0 = time.perf_counter()
    M = A.convert(mtype) if mtype != "aij" else A
    eps = spectrum.sinvert_eps(M, k, -spectrum.ZERO_TOL * norm, 0.1 * tol * norm, defl)
    eps.solve()
    seconds = time.perf_counter() - t0
    nconv = eps.getConverged()
    lam, res = [], []
    v = A.createVecRight()
    for i in range(min(nconv, k)):
        lam.append(eps.getEigenpair(i, v).real)
        res.append(eps.computeError(i, SLEPc.EPS.ErrorType.ABSOLUTE) / norm)
    fill = None
    if pkg == "mumps":
        fill = spectrum.mumps_stats(eps.getST().getKSP().getPC().getFactorMatrix()).get(
            "factor_entries")
    its = eps.getIterationNumber()
    for obj in [eps, v, *defl] + ([M] if M is not A else []) + [A]:
        obj.destroy()
    for key in values:
        opts.delValue(spectrum.PREFIX + key)
    order = np.argsort(lam)
    return np.array(lam)[order], np.array(res)[order], seconds, {"iterations": its,
                                                                   "factor_entries": fill}


def run_scipy_eigsh(system, k):
    import scipy.sparse
    import scipy.sparse.linalg

    d = system.d
    t0 = time.perf_counter()
    blocks = system.blocks("full")
    rows, cols, vals = [], [], []
    for a, b in ((system.i, system.i), (system.j, system.j), (system.i, system.j),
                 (system.j, system.i)):
        sign = 1.0 if a is b else -1.0
        for p in range(d):
            for q in range(d):
                rows.append(a * d + p)
                cols.append(b * d + q)
                vals.append(sign * blocks[:, p, q])
    S = scipy.sparse.csc_matrix((np.concatenate(vals), (np.concatenate(rows),
                                                        np.concatenate(cols))),
                                shape=(system.dof, system.dof))
    norm = abs(S).sum(axis=1).max()
    lam, V = scipy.sparse.linalg.eigsh(S, k=k + d, sigma=-1e-9 * norm, which="LM")
    seconds = time.perf_counter() - t0
    order = np.argsort(lam)[d:]
    res = np.linalg.norm(S @ V[:, order] - V[:, order] * lam[order], axis=0) / norm
    return lam[order], seconds, res


def best_of(repeat, fn):
    """fn() ``repeat`` times; the result of the fastest run (the machine is shared)."""
    runs = [fn() for _ in range(repeat)]
    return min(runs, key=lambda r: r[2])


def stage_eig(paths, k, cache_dir, log, repeat=2, knobs=("tol", "ncv", "factor", "mpd", "peer")):
    rows = []
    for path in paths:
        system = load(path)
        truth, t_dense = dense_truth(system, cache_path(cache_dir, path))
        ref = truth[:k]
        from parjam.vib import spectrum

        norm = float(np.abs(spectrum.dense_matrix(system, "full")).sum(axis=1).max())
        log(f"eig: {path}: N' = {system.n}, dense {t_dense:.1f} s")
        grid = ([("tol", tol, dict(tol=tol)) for tol in (1e-4, 1e-6, 1e-8, 1e-10, 1e-12)]
                + [("ncv", ncv, dict(tol=1e-10, ncv=ncv)) for ncv in
                   (k + 10, k + k // 2, 2 * k, 3 * k)]
                + [("factor", f, dict(tol=1e-10, factor=f)) for f in FACTORS]
                # mpd bounds the projected problem when k is large: 4k modes, ncv = 4k + mpd
                + [("mpd", f"{mpd} (k={4 * k})",
                    dict(tol=1e-10, mpd=mpd, ncv=4 * k + mpd, kk=4 * k)) for mpd in (k, 2 * k)]
                + [("mpd", f"none, ncv {6 * k} (k={4 * k})", dict(tol=1e-10, kk=4 * k))])
        for knob, value, kw in grid:
            if knob not in knobs:
                continue
            kk = kw.pop("kk", k)
            ref = truth[:kk]
            try:
                lam, res, sec, info = best_of(repeat, lambda: run_sinvert(system, kk, **kw))
            except Exception as exc:  # a package missing or failing: recorded, not fatal
                rows.append({"N": system.n, "knob": knob, "value": value, "error": str(exc)})
                log(f"eig: {knob}={value}: failed ({str(exc).splitlines()[-1]})")
                continue
            m = min(len(lam), kk)
            err = float(np.max(np.abs(lam[:m] / ref[:m] - 1))) if m else float("nan")
            abs_err = float(np.max(np.abs(lam[:m] - ref[:m]))) / norm if m else float("nan")
            rows.append({"N": system.n, "dof": system.dof, "knob": knob, "value": value,
                         "seconds": sec, "converged": int(len(lam)), "max_residual":
                         float(res.max()) if len(res) else float("nan"), "max_rel_error": err,
                         "max_abs_error_over_norm": abs_err,
                         "dense_seconds": t_dense, **info})
            log(f"eig: {knob}={value}: {sec:.2f} s, residual {rows[-1]['max_residual']:.1e}, "
                f"error {err:.1e}")
        if "peer" not in knobs:
            continue
        ref = truth[:k]
        lam, sec, res = min((run_scipy_eigsh(system, k) for _ in range(repeat)),
                            key=lambda r: r[1])
        rows.append({"N": system.n, "dof": system.dof, "knob": "peer", "value": "scipy eigsh",
                     "seconds": sec, "converged": len(lam), "max_residual": float(res.max()),
                     "max_abs_error_over_norm": float(np.max(np.abs(lam - ref))) / norm,
                     "max_rel_error": float(np.max(np.abs(lam / ref - 1))),
                     "dense_seconds": t_dense})
        log(f"eig: scipy eigsh {sec:.2f} s")
    return rows


# --- D(omega) -------------------------------------------------------------------------------------
def dos_metrics(omega_lam_edges, density, d0, wstar, truth):
    edges = omega_lam_edges
    return {"L1": float(np.sum(np.abs(density - truth["density"]) * np.diff(edges))),
            "D0_rel_error": abs(d0 / truth["D0"] - 1), "omega_star_error":
            abs(wstar - truth["omega_star"])}


def stage_dos(paths, moments, probes, cache_dir, log, bins=40):
    from parjam import env
    from parjam.vib import kpm, observables, spectrum

    PETSc = env.petsc()
    comm = PETSc.COMM_WORLD
    rows = []
    for path in paths:
        system = load(path)
        lam, t_dense = dense_truth(system, cache_path(cache_dir, path))
        w = observables.frequency(lam)
        edges = observables.dos_edges(float(w.max()) * 1.01, bins)
        _, dens = observables.density_of_states(w, system.n_modes, edges)
        d0, wstar, window = observables.dos_summary(w, system.n_modes)
        truth = {"density": dens, "D0": d0, "omega_star": wstar}
        nnz = system.d ** 2 * (system.n + 2 * len(system.r))
        base = {"N": system.n, "dof": system.dof, "nnz": nnz,
                # memory models (bytes): the dense matrix; KPM's AIJ matrix + 4 vectors
                "dense_bytes": 8 * system.dof ** 2, "kpm_bytes": 12 * nnz + 32 * system.dof}
        rows.append({**base, "method": "dense", "seconds": t_dense, "L1": 0.0,
                     "D0": d0, "omega_star": wstar})
        log(f"dos: {path}: N' = {system.n}, dense {t_dense:.1f} s, D0 {d0:.4f}, "
            f"omega* {wstar:.4f}")
        # slicing: the lowest 10 % of the modes (the low-frequency part, omega*)
        wcut = float(np.quantile(w, 0.1))
        spec = spectrum.compute(comm, system, "full", window=(0.0, wcut), method="slice")
        low = edges[edges <= wcut]
        _, ds = observables.density_of_states(spec.frequency, system.n_modes, low)
        rows.append({**base, "method": "slice", "seconds": spec.seconds, "window": wcut,
                     "count": len(spec.eigenvalue), "dense_count": int(np.sum(w <= wcut)),
                     "L1_window": float(np.sum(np.abs(ds - dens[:len(ds)]) * np.diff(low))),
                     "max_eig_error": float(np.max(np.abs(spec.eigenvalue -
                                                          lam[:len(spec.eigenvalue)])))})
        log(f"dos: slice to omega {wcut:.3f}: {spec.seconds:.1f} s, "
            f"{len(spec.eigenvalue)} modes (dense {rows[-1]['dense_count']})")
        # KPM: one run at the largest moments x probes, sub-grids evaluated from it
        P, M = max(probes), max(moments)
        t0 = time.perf_counter()
        res = kpm.compute(comm, system, "full", M, P, seed=1)
        t_all = time.perf_counter() - t0
        t_bounds = _time_bounds(comm, system)  # assembly + bounds
        per_matvec = max(t_all - t_bounds, 0.0) / (P * ((M + 1) // 2))
        for m in moments:
            for p in probes:
                sub = kpm.KPMResult(
                    moments=np.r_[1.0, res.probe_moments[:p, 1:m].mean(axis=0)],
                    probe_moments=res.probe_moments[:p, :m], a=res.a, b=res.b,
                    n_modes=res.n_modes, matrix="full", probe_kind="rademacher", seed=1)
                k0, ks, _ = kpm.dos_summary(sub, plateau=window)
                rows.append({**base, "method": "kpm", "moments": m, "probes": p,
                             "seconds": t_bounds + per_matvec * p * ((m + 1) // 2),
                             "D0": k0, "omega_star": ks,
                             **dos_metrics(edges, sub.binned(edges), k0, ks, truth)})
        for m, p in [(min(moments), min(probes)), (sorted(moments)[len(moments) // 2],
                                                   sorted(probes)[len(probes) // 2])]:
            t0 = time.perf_counter()
            kpm.compute(comm, system, "full", m, p, seed=1)
            rows.append({**base, "method": "kpm-timed", "moments": m, "probes": p,
                         "seconds": time.perf_counter() - t0,
                         "model_seconds": t_bounds + per_matvec * p * ((m + 1) // 2)})
        log(f"dos: kpm {M} x {P}: {t_all:.1f} s ({per_matvec * 1e3:.2f} ms per product)")
    return rows


def _time_bounds(comm, system):
    """The fixed cost of a KPM run: assembly of the matrix and the Lanczos bounds."""
    from parjam.vib import kpm, spectrum

    t0 = time.perf_counter()
    A = spectrum.dynamical_matrix(comm, system, "full")
    kpm.spectral_bounds(A, system.d, "full", 1)
    sec = time.perf_counter() - t0
    A.destroy()
    return sec


# --- method choice (modes --method auto) -------------------------------------------------------------
def stage_auto(paths, log, repeat=2):
    """spectrum.compute by dense and by sinvert for a few k at each size (what auto chooses
    between), timed as the command runs them (observables included), best of ``repeat``."""
    from parjam import env
    from parjam.vib import spectrum

    comm = env.petsc().COMM_SELF
    rows = []
    for path in paths:
        system = load(path)
        for k in sorted({10, 50, max(1, system.n_modes // 10), system.n_modes // 3}):
            if k > system.n_modes:
                continue
            rec = {"N": system.n, "dof": system.dof, "k": k}
            for method in ("dense", "sinvert"):
                if method == "dense" and system.dof > 13000:
                    continue
                best = None
                for _ in range(repeat):
                    spec = spectrum.compute(comm, system, "full", k=k, method=method)
                    best = spec if best is None or spec.seconds < best.seconds else best
                rec[f"{method}_seconds"] = best.seconds
                rec[f"{method}_max_residual"] = float(best.error.max())
                rec[f"{method}_complete"] = bool(best.complete)
            rows.append(rec)
            log(f"auto: N' {system.n} k {k}: " + ", ".join(
                f"{m} {rec.get(m + '_seconds', float('nan')):.2f} s" for m in ("dense", "sinvert")))
    return rows


# --- minimisation tolerance -----------------------------------------------------------------------
def stage_ftol(phic_path, dphis, ftols, k, log):
    from parjam import env
    from parjam.files import h5md
    from parjam.net import network
    from parjam.vib import spectrum
    from parjam.pack.packing import JamSettings, Jammer

    PETSc = env.petsc()
    base = h5md.read_packing(phic_path)
    phi_c = base.phi
    rows = []
    for dphi in dphis:
        states = {}
        for ftol in sorted(ftols):
            jam = Jammer(PETSc.COMM_SELF, base, JamSettings(ftol=ftol))
            t0 = time.perf_counter()
            res = jam.relax(phi_c + dphi)
            sec = time.perf_counter() - t0
            pack = jam.pack.copy()
            jam.destroy()
            net = network.analyze(pack)
            try:
                system = spectrum.active_system(pack, net)
                spec = spectrum.compute(PETSc.COMM_SELF, system, "full", k=k, method="dense",
                                        tol=0.0099)
            except Exception as exc:  # e.g. too few contacts (hypostatic): recorded
                states[ftol] = {"dphi": dphi, "ftol": ftol, "seconds": sec, "error": str(exc),
                                "max_force": float(net.max_force), "dz": float(net.dz),
                                "pressure": float(net.pressure), "lowest": [],
                                "n_negative": -1, "fire_steps": int(res.fire_steps),
                                "newton_steps": int(res.newton_steps)}
                log(f"ftol: dphi {dphi:g} ftol {ftol:g}: max|F| {net.max_force:.1e}: {exc}")
                continue
            states[ftol] = {"dphi": dphi, "ftol": ftol, "seconds": sec,
                            "max_force": float(net.max_force), "dz": float(net.dz),
                            "pressure": float(net.pressure), "n_active": int(net.n_active),
                            "lowest": spec.eigenvalue.tolist(),
                            "n_negative": int(spec.n_negative),
                            "fire_steps": int(res.fire_steps),
                            "newton_steps": int(res.newton_steps)}
            log(f"ftol: dphi {dphi:g} ftol {ftol:g}: max|F| {net.max_force:.1e}, "
                f"{sec:.1f} s, dz {net.dz:.4f}, p {net.pressure:.3e}, "
                f"{spec.n_negative} negative, lambda_1 {spec.eigenvalue[0]:.3e}")
        ref = states[min(ftols)]
        for ftol, st in states.items():
            lam, lref = np.array(st["lowest"]), np.array(ref["lowest"])
            m = min(len(lam), len(lref))
            st["eig_rel_error"] = (float(np.max(np.abs(lam[:m] / lref[:m] - 1))) if m
                                   else float("nan"))
            st["dz_error"] = abs(st["dz"] - ref["dz"])
            st["p_rel_error"] = abs(st["pressure"] / ref["pressure"] - 1)
            rows.append(st)
    return rows


def cache_path(cache_dir, path):
    if not cache_dir:
        return None
    os.makedirs(cache_dir, exist_ok=True)
    import hashlib

    with open(path, "rb") as f:
        digest = hashlib.sha256(f.read()).hexdigest()[:16]
    return os.path.join(cache_dir, f"dense_{digest}.npz")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--eig", nargs="*", default=[], help="packings for the eigensolver knobs")
    ap.add_argument("--k", type=int, default=50)
    ap.add_argument("--repeat", type=int, default=2, help="eig: best of this many runs")
    ap.add_argument("--knobs", nargs="+", default=["tol", "ncv", "factor", "mpd", "peer"],
                    help="eig: which knobs to vary")
    ap.add_argument("--dos", nargs="*", default=[], help="packings for D(omega)")
    ap.add_argument("--moments", type=int, nargs="+", default=[64, 128, 256, 512, 1024])
    ap.add_argument("--probes", type=int, nargs="+", default=[2, 8, 32])
    ap.add_argument("--auto", nargs="*", default=[], help="packings for dense vs sinvert "
                    "(what modes --method auto chooses between)")
    ap.add_argument("--ftol-phic", help="a converged phi_c packing for the ftol stage")
    ap.add_argument("--ftols", type=float, nargs="+",
                    default=[1e-4, 1e-6, 1e-8, 1e-10, 1e-13])
    ap.add_argument("--dphis", type=float, nargs="+", default=[1e-2, 1e-6])
    ap.add_argument("--cache", default="bench-out/dense-cache")
    ap.add_argument("--json", required=True, help="raw results (JSON)")
    ap.add_argument("--md", help="write tables into this page (between the generated markers)")
    ap.add_argument("--img", default="docs/img", help="directory of the Pareto plots")
    ap.add_argument("--merge", nargs="*", default=[], help="JSON files of earlier runs to "
                    "merge (their stages) before reporting")
    args = ap.parse_args()

    from parjam import env

    env.init()
    t0 = time.time()

    def log(msg):
        print(f"[{time.time() - t0:7.1f} s] {msg}", file=sys.stderr, flush=True)

    out = {"machine": {"python": platform.python_version(), "node": platform.node(),
                       "cpus": os.cpu_count(), "load": os.getloadavg()},
           "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    if os.path.exists(args.json):
        with open(args.json) as f:
            out.update({key: val for key, val in json.load(f).items()
                        if key in ("eig", "dos", "ftol", "auto")})

    def save():
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1, default=float)

    if args.eig:
        out["eig"] = stage_eig(args.eig, args.k, args.cache, log, args.repeat, args.knobs)
        save()
    if args.dos:
        out["dos"] = stage_dos(args.dos, args.moments, args.probes, args.cache, log)
        save()
    if args.auto:
        out["auto"] = stage_auto(args.auto, log, args.repeat)
        save()
    if args.ftol_phic:
        out["ftol"] = stage_ftol(args.ftol_phic, args.dphis, args.ftols, 20, log)
        save()
    for path in args.merge:  # stages of earlier runs; rows of a stage run twice are joined
        with open(path) as f:
            for key, val in json.load(f).items():
                if key in ("eig", "dos", "ftol", "auto"):
                    out[key] = out.get(key, []) + [r for r in val if r not in out.get(key, [])]
    save()
    if args.md:
        report(out, args.md, args.img)


# --- report: tables and Pareto plots ----------------------------------------------------------------
BEGIN, END = "<!-- generated by scripts/bench_speed_accuracy.py: begin -->", \
    "<!-- generated by scripts/bench_speed_accuracy.py: end -->"


def pareto(points):
    """Indices of the (time, error) points not dominated by a faster and more accurate one."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], np.inf
    for i in order:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


def fmt(x, spec=".2g"):
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "-"
    return format(x, spec) if isinstance(x, (int, float)) else str(x)


def eig_section(rows, img):
    import matplotlib.pyplot as plt

    lines = ["## Eigensolver: tolerance, ncv, factorisation (lowest k modes against dense)", "",
             "| N' | dof | knob | value | time (s) | vs dense eigvalsh | converged | max residual "
             "| max abs error / norm | max rel error | MUMPS factor entries |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['N']} | | {r['knob']} | {r['value']} | failed: "
                         f"{r['error'].splitlines()[-1][:60]} | | | | | | |")
            continue
        lines.append(f"| {r['N']} | {r['dof']} | {r['knob']} | {r['value']} | "
                     f"{r['seconds']:.2f} | {r['dense_seconds'] / r['seconds']:.1f}x faster | "
                     f"{r['converged']} | {fmt(r.get('max_residual'), '.1e')} | "
                     f"{fmt(r.get('max_abs_error_over_norm'), '.1e')} | "
                     f"{fmt(r['max_rel_error'], '.1e')} | {fmt(r.get('factor_entries'), 'd')} |")
    sizes = sorted({r["N"] for r in rows})
    fig, axes = plt.subplots(1, len(sizes), figsize=(5.5 * len(sizes), 4.2), squeeze=False)
    marks = {"tol": "o", "ncv": "s", "factor": "^", "mpd": "D", "peer": "*"}
    for ax, n in zip(axes[0], sizes):
        sub = [r for r in rows if r["N"] == n and "error" not in r]
        for knob, mk in marks.items():
            pts = [r for r in sub if r["knob"] == knob]
            if not pts:
                continue
            y = [r.get("max_residual", r["max_rel_error"]) for r in pts]
            ax.scatter([r["seconds"] for r in pts], y, marker=mk, s=50, label=knob)
            for r, yy in zip(pts, y):
                ax.annotate(str(r["value"]).replace("-cholesky", "").replace("-lu", " LU"),
                            (r["seconds"], yy), fontsize=6, xytext=(3, 2),
                            textcoords="offset points")
        pts = [(r["seconds"], r.get("max_residual", 1.0)) for r in sub if r["knob"] != "peer"]
        front = sorted(pts[i] for i in pareto(pts))
        ax.plot(*zip(*front), "k--", lw=0.8, label="Pareto front")
        dense = sub[0]["dense_seconds"]
        ax.axvline(dense, color="grey", lw=0.8)
        ax.text(dense, ax.get_ylim()[1], " dense eigvalsh", fontsize=7, va="top", rotation=90)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("max residual ||Dv - lambda v|| / ||D||")
        ax.set_title(f"lowest {sub[0]['converged']} modes, N' = {n}")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(os.path.join(img, "speed_eig.png"), dpi=110)
    plt.close(fig)
    return lines + ["", "![eigensolver Pareto](img/speed_eig.png)", ""]


def dos_section(rows, img):
    import matplotlib.pyplot as plt

    lines = ["## D(omega): dense LAPACK, spectrum slicing, KPM", ""]
    sizes = sorted({r["N"] for r in rows})
    for n in sizes:
        sub = [r for r in rows if r["N"] == n]
        dense = next(r for r in sub if r["method"] == "dense")
        sl = next((r for r in sub if r["method"] == "slice"), None)
        lines += [f"### N' = {n} ({dense['dof']} dof)", "",
                  f"- dense eigvalsh (all {dense['dof'] - 3} modes, the truth): "
                  f"{dense['seconds']:.1f} s, D0 = {dense['D0']:.4f}, "
                  f"omega* = {dense['omega_star']:.4f}"]
        if "dense_bytes" in dense:
            lines.append(f"- memory (model): dense matrix {dense['dense_bytes'] / 2**20:.0f} MB; "
                         f"KPM (AIJ matrix + 4 vectors) {dense['kpm_bytes'] / 2**20:.1f} MB")
        if sl:
            lines.append(f"- slicing, the lowest 10 % (omega <= {sl['window']:.3f}): "
                         f"{sl['seconds']:.1f} s ({dense['seconds'] / sl['seconds']:.1f}x "
                         f"dense), {sl['count']} modes (dense {sl['dense_count']}), L1 in the "
                         f"window {sl['L1_window']:.1e}, max eigenvalue error "
                         f"{sl['max_eig_error']:.1e}")
        for r in sub:
            if r["method"] == "kpm-timed":
                lines.append(f"- KPM {r['moments']} x {r['probes']} timed directly: "
                             f"{r['seconds']:.2f} s (cost model {r['model_seconds']:.2f} s)")
        lines += ["", "| moments | probes | time (s) | vs dense | L1 | D0 rel. error | "
                  "omega* error | omega* error / omega* |", "|---|---|---|---|---|---|---|---|"]
        for r in sub:
            if r["method"] == "kpm":
                lines.append(f"| {r['moments']} | {r['probes']} | {r['seconds']:.2f} | "
                             f"{dense['seconds'] / r['seconds']:.1f}x | {r['L1']:.3f} | "
                             f"{r['D0_rel_error']:.3f} | {r['omega_star_error']:.4f} | "
                             f"{r['omega_star_error'] / dense['omega_star']:.2f} |")
        lines.append("")
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for n, colour in zip(sizes, ["C0", "C1", "C2", "C3", "C4"]):
        sub = [r for r in rows if r["N"] == n]
        kp = [r for r in sub if r["method"] == "kpm"]
        dense = next(r for r in sub if r["method"] == "dense")
        for ax, key in zip(axes, ("L1", "omega_star_error")):
            pts = [(r["seconds"], r[key]) for r in kp]
            ax.scatter(*zip(*pts), s=[8 + 4 * r["probes"] ** 0.5 * 3 for r in kp],
                       c=colour, alpha=0.6, label=f"KPM, N' = {n}")
            front = sorted(pts[i] for i in pareto(pts))
            ax.plot(*zip(*front), color=colour, lw=1)
            ax.axvline(dense["seconds"], color=colour, ls=":", lw=1.2)
    axes[0].set_ylabel("L1 distance of D(omega) to dense (0..2)")
    axes[1].set_ylabel("|omega* - omega*_dense|")
    for ax in axes:
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("time (s); dotted: dense eigvalsh of the same N'")
        ax.legend(fontsize=7)
    axes[0].set_title("KPM: moments x probes (marker size ~ probes)")
    fig.tight_layout()
    fig.savefig(os.path.join(img, "speed_dos.png"), dpi=110)
    plt.close(fig)
    return lines + ["![D(omega) Pareto](img/speed_dos.png)", ""]


def ftol_section(rows, img):
    import matplotlib.pyplot as plt

    lines = ["## Minimisation tolerance (parjam pack --ftol)", "",
             "| dphi | ftol | max abs F reached | time (s) | FIRE / Newton steps | dz | "
             "dz error | p rel. error | 20 lowest: max rel. error | negative modes |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        neg = "hypostatic: " + r["error"].split(":")[0] if "error" in r else r["n_negative"]
        lines.append(f"| {r['dphi']:g} | {r['ftol']:g} | {r['max_force']:.1e} | "
                     f"{r['seconds']:.2f} | {r['fire_steps']} / {r['newton_steps']} | "
                     f"{r['dz']:.4f} | {r['dz_error']:.1e} | {r['p_rel_error']:.1e} | "
                     f"{fmt(r['eig_rel_error'], '.1e')} | {neg} |")
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, dphi in zip(axes, sorted({r["dphi"] for r in rows}, reverse=True)):
        sub = sorted([r for r in rows if r["dphi"] == dphi and r["ftol"] > min(
            x["ftol"] for x in rows)], key=lambda r: r["max_force"])
        if not sub:
            continue
        F = [r["max_force"] for r in sub]
        for key, label in (("eig_rel_error", "20 lowest lambda: max rel. error"),
                           ("dz_error", "dz error"), ("p_rel_error", "p rel. error")):
            ax.plot(F, [max(r[key], 1e-16) if np.isfinite(r[key]) else np.nan for r in sub],
                    "o-", label=label)
        for r in sub:
            ax.annotate(f"{r['seconds']:.2f} s", (r["max_force"], 1e-16), fontsize=6,
                        rotation=90, xytext=(2, 2), textcoords="offset points")
            if r["n_negative"] != 0:
                ax.axvspan(r["max_force"] * 0.7, r["max_force"] * 1.4, color="red", alpha=0.15)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("max |F| reached (red: negative modes or hypostatic; labels: time; "
                      "0 drawn at 1e-16)", fontsize=8)
        ax.set_title(f"dphi = {dphi:g}")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(os.path.join(img, "speed_ftol.png"), dpi=110)
    plt.close(fig)
    return lines + ["", "![ftol Pareto](img/speed_ftol.png)", ""]


def auto_section(rows):
    lines = ["## dense against sinvert for the k lowest modes (what `modes --method auto` picks)",
             "", "`spectrum.compute` as `parjam modes` runs it (observables included), 1 rank.",
             "", "| N' | dof | k | dense (s) | sinvert (s) | dense / sinvert | dense residual | "
             "sinvert residual |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        ratio = (r["dense_seconds"] / r["sinvert_seconds"] if "dense_seconds" in r
                 else float("nan"))
        lines.append(f"| {r['N']} | {r['dof']} | {r['k']} | {fmt(r.get('dense_seconds'), '.2f')}"
                     f" | {r['sinvert_seconds']:.2f} | {fmt(ratio, '.2f')} | "
                     f"{fmt(r.get('dense_max_residual'), '.1e')} | "
                     f"{r['sinvert_max_residual']:.1e} |")
    return lines + [""]


def report(results, md, img):
    """Write the generated part of ``md`` (between the markers; text outside them is kept)."""
    os.makedirs(img, exist_ok=True)
    body = [BEGIN, "", f"Generated {results.get('date', '')}, load "
            f"{fmt(results.get('machine', {}).get('load', [np.nan])[0], '.1f')} on "
            f"{results.get('machine', {}).get('cpus', '?')} cores (shared).", ""]
    if results.get("eig"):
        body += eig_section(results["eig"], img)
    if results.get("dos"):
        body += dos_section(results["dos"], img)
    if results.get("auto"):
        body += auto_section(results["auto"])
    if results.get("ftol"):
        body += ftol_section(results["ftol"], img)
    body.append(END)
    text = "\n".join(body) + "\n"
    if os.path.exists(md):
        old = open(md).read()
        if BEGIN in old and END in old:
            text = old.split(BEGIN)[0] + text.rstrip("\n") + old.split(END, 1)[1]
    with open(md, "w") as f:
        f.write(text)


if __name__ == "__main__":
    main()
