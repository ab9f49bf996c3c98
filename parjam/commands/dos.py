"""``parjam dos``: ensemble-averaged D(omega), D0 and omega* over spectrum files."""

import os
import sys

import numpy as np

from parjam.commands import parse_pair
from parjam.errors import ParjamError
from parjam.spectrum import MATRICES


def add_parser(sub):
    p = sub.add_parser(
        "dos", help="ensemble-averaged density of states over spectrum files",
        description="D(omega) per mode of each spectrum file (from parjam modes) on common bins "
        "up to the lowest of the files' highest computed frequencies, averaged with standard "
        "errors; D0 and omega* per file (definitions in docs/spectra.md) and their means.")
    p.add_argument("spectra", nargs="+", help="spectrum files of one matrix kind (with --method "
                   "kpm: packing files)")
    p.add_argument("--bins", type=int, default=40, help="number of bins (40)")
    p.add_argument("--log-bins", action="store_true", help="logarithmic bins")
    p.add_argument("--omega-min", type=float, help="lowest edge of log bins")
    p.add_argument("--plateau", help="plateau window W1,W2 for D0 and omega*")
    p.add_argument("--out", required=True, help="HDF5 file for the averaged D(omega)")
    p.add_argument("--plot", help="PNG of the averaged D(omega) with error bars")
    k = p.add_argument_group("stochastic D(omega) of packings (--method kpm, docs/speed-accuracy.md)")
    k.add_argument("--method", default="spectra", choices=("spectra", "kpm"),
                   help="spectra: average spectrum files (default); kpm: D(omega) of packing "
                   "files by the kernel polynomial method (distributed MatMult only, no "
                   "eigensolver: for N beyond dense and slicing)")
    k.add_argument("--matrix", default="full", choices=MATRICES,
                   help="kpm: matrix of Eq. (1) (default full)")
    k.add_argument("--moments", type=int, default=256, help="kpm: Chebyshev moments (256)")
    k.add_argument("--probes", type=int, default=16, help="kpm: random probe vectors (16)")
    k.add_argument("--seed", type=int, default=0, help="kpm: probe seed (0); the same on any "
                   "number of ranks")
    k.add_argument("--probe-kind", default="rademacher", choices=("rademacher", "gaussian"),
                   help="kpm: probe entries +-1 (default) or Gaussian")
    k.add_argument("--kpm-bounds", help="kpm: lambda interval A,B enclosing the spectrum "
                   "(default: Lanczos estimate)")
    p.set_defaults(run=run)


def ensemble(specs, bins, log, omega_min, plateau):
    """Per-file D(omega) on common edges, D0 and omega*; their means and standard errors."""
    from parjam import observables

    kinds = {s["attrs"]["matrix"] for s in specs}
    if len(kinds) != 1:
        raise ParjamError(f"spectrum files mix matrices {sorted(kinds)}: average one kind")
    # vibrations only: zero modes (floppy, |lambda| <= zero_tol) and unstable ones left out
    omegas = [s["frequency"][s["eigenvalue"] > float(s["attrs"].get("zero_tol", 0.0))]
              for s in specs]
    if any(len(w) == 0 for w in omegas):
        raise ParjamError("a spectrum file holds no positive frequency")
    top = min(float(w.max()) for w in omegas)
    edges = observables.dos_edges(top, bins, log, omega_min)
    dens, d0s, stars = [], [], []
    for s, w in zip(specs, omegas):
        n_modes = int(s["attrs"]["n_modes_total"])
        centres, dn = observables.density_of_states(w, n_modes, edges)
        d0, wstar, _ = observables.dos_summary(w, n_modes, plateau)
        dens.append(dn)
        d0s.append(d0)
        stars.append(wstar)
    mean, err = observables.ensemble_mean(dens)
    return {"omega": centres, "edges": edges, "density": mean, "density_error": err,
            "D0_each": np.array(d0s), "omega_star_each": np.array(stars),
            "matrix": kinds.pop()}


def run(args):
    from parjam import env, io, modes_io, observables

    PETSc = env.petsc()
    rank = PETSc.COMM_WORLD.getRank()
    if not 1 <= args.bins <= 1_000_000:
        raise ParjamError(f"--bins must lie in [1, 1000000], got {args.bins}")
    if os.path.isdir(args.out):
        raise ParjamError(f"--out {args.out} is a directory")
    plateau = parse_pair(args.plateau, "--plateau") if args.plateau else None
    if getattr(args, "method", "spectra") == "kpm":
        return run_kpm(args, plateau)
    specs = [modes_io.read_spectrum(p) for p in args.spectra]
    res = ensemble(specs, args.bins, args.log_bins, args.omega_min, plateau)
    d0, d0_err = observables.ensemble_mean(res["D0_each"][:, None])
    ws, ws_err = observables.ensemble_mean(res["omega_star_each"][:, None])
    if rank != 0:
        return 0
    dos = {"omega": res["omega"], "edges": res["edges"], "density": res["density"],
           "density_error": res["density_error"], "binning": "log" if args.log_bins else "linear",
           "normalisation": "per mode: counts / ((d N' - d) * bin width), then averaged",
           "matrix": res["matrix"], "n_files": len(specs), "D0": float(d0[0]),
           "D0_error": float(d0_err[0]), "omega_star": float(ws[0]),
           "omega_star_error": float(ws_err[0]), "D0_each": res["D0_each"],
           "omega_star_each": res["omega_star_each"]}
    try:
        with io.atomic_h5(args.out) as f:
            io.write_h5md_header(f, io.provenance(PETSc.COMM_WORLD.getSize(),
                                                  {"command": "dos", "files": args.spectra}))
            modes_io.write_dos(f, dos)
    except OSError as exc:
        raise ParjamError(f"{args.out}: cannot write ({exc})", collective=False) from None
    print(f"{res['matrix']}: {len(specs)} spectra, D0 = {d0[0]:.4g} +- {d0_err[0]:.2g}, "
          f"omega* = {ws[0]:.4g} +- {ws_err[0]:.2g}", flush=True)
    if args.plot:
        from parjam.plot.spectra import ensemble_dos_figure

        ensemble_dos_figure(res["omega"], res["density"], res["density_error"], args.plot,
                            res["matrix"], ws[0])
    return 0


def kpm_ensemble(comm, paths, args, plateau, progress):
    """KPM D(omega) of each packing on common bins (up to the lowest upper bound of the files),
    D0 and omega* each; mean and standard error over files (over probes for one file)."""
    from parjam import io, kpm, observables, spectrum

    bounds = parse_pair(args.kpm_bounds, "--kpm-bounds") if args.kpm_bounds else None
    results = []
    for path in paths:
        system = spectrum.active_system(io.read_packing(path))
        progress(f"{path}: N' = {system.n}, {len(system.r)} contacts")
        results.append(kpm.compute(comm, system, args.matrix, args.moments, args.probes,
                                   args.seed, args.probe_kind, bounds, progress))
    top = min(r.omega_max for r in results)
    edges = observables.dos_edges(top, args.bins, args.log_bins, args.omega_min)
    dens, errs, d0s, stars = [], [], [], []
    for r in results:
        dn, err = r.binned_with_error(edges)
        d0, wstar, _ = kpm.dos_summary(r, plateau)
        dens.append(dn)
        errs.append(err)
        d0s.append(d0)
        stars.append(wstar)
    mean, err = observables.ensemble_mean(dens)
    if len(results) == 1:
        err = errs[0]
    return results, edges, mean, err, np.array(d0s), np.array(stars)


def run_kpm(args, plateau):
    from parjam import env, io, modes_io, observables
    from parjam.progress import Progress

    PETSc = env.petsc()
    comm = PETSc.COMM_WORLD
    progress = Progress(comm.tompi4py(), False, "dos: ")
    results, edges, mean, err, d0s, stars = kpm_ensemble(comm, args.spectra, args, plateau,
                                                         progress)
    d0, d0_err = observables.ensemble_mean(d0s[:, None])
    ws, ws_err = observables.ensemble_mean(stars[:, None])
    if comm.getRank() != 0:
        return 0
    for path, r in zip(args.spectra, results):
        if not r.fold_below_zero and r.weight_below_zero > 1e-3:
            print(f"parjam: warning: {path}: {r.weight_below_zero:.1%} of the modes lie below "
                  f"lambda = 0 (unstable packing or indefinite matrix): left out of D(omega)",
                  file=sys.stderr, flush=True)
    centres = (np.sqrt(edges[1:] * edges[:-1]) if args.log_bins
               else 0.5 * (edges[1:] + edges[:-1]))
    dos = {"omega": centres, "edges": edges, "density": mean, "density_error": err,
           "binning": "log" if args.log_bins else "linear",
           "normalisation": "per mode: KPM fraction of the d N' - d modes per bin / bin width, "
                            "averaged over files (error over files, or over probes for one)",
           "matrix": args.matrix, "n_files": len(results), "method": "kpm",
           "n_moments": args.moments, "n_probes": args.probes, "seed": args.seed,
           "probe_kind": args.probe_kind, "kernel": "Jackson",
           "kpm_bounds": np.array([[r.a, r.b] for r in results]),
           "kpm_moments": np.array([r.moments for r in results]),
           "weight_below_zero": np.array([r.weight_below_zero for r in results]),
           "seconds": np.array([r.seconds for r in results]),
           "D0": float(d0[0]), "D0_error": float(d0_err[0]), "omega_star": float(ws[0]),
           "omega_star_error": float(ws_err[0]), "D0_each": d0s, "omega_star_each": stars}
    try:
        with io.atomic_h5(args.out) as f:
            io.write_h5md_header(f, io.provenance(comm.getSize(),
                                                  {"command": "dos", "files": args.spectra}))
            modes_io.write_dos(f, dos)
    except OSError as exc:
        raise ParjamError(f"{args.out}: cannot write ({exc})", collective=False) from None
    print(f"{args.matrix}: KPM ({args.moments} moments x {args.probes} probes) of "
          f"{len(results)} packings, D0 = {d0[0]:.4g} +- {d0_err[0]:.2g}, "
          f"omega* = {ws[0]:.4g} +- {ws_err[0]:.2g}, {sum(r.seconds for r in results):.2f} s",
          flush=True)
    if args.plot:
        from parjam.plot.spectra import ensemble_dos_figure

        ensemble_dos_figure(centres, mean, err, args.plot, args.matrix, ws[0])
    return 0
