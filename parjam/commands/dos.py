"""``parjam dos``: ensemble-averaged D(omega), D0 and omega* over spectrum files."""

import numpy as np

from parjam.errors import ParjamError


def add_parser(sub):
    p = sub.add_parser(
        "dos", help="ensemble-averaged density of states over spectrum files",
        description="D(omega) per mode of each spectrum file (from parjam modes) on common bins "
        "up to the lowest of the files' highest computed frequencies, averaged with standard "
        "errors; D0 and omega* per file (definitions in docs/spectra.md) and their means.")
    p.add_argument("spectra", nargs="+", help="spectrum files of one matrix kind")
    p.add_argument("--bins", type=int, default=40, help="number of bins (40)")
    p.add_argument("--log-bins", action="store_true", help="logarithmic bins")
    p.add_argument("--omega-min", type=float, help="lowest edge of log bins")
    p.add_argument("--plateau", help="plateau window W1,W2 for D0 and omega*")
    p.add_argument("--out", required=True, help="HDF5 file for the averaged D(omega)")
    p.add_argument("--plot", help="PNG of the averaged D(omega) with error bars")
    p.set_defaults(run=run)


def ensemble(specs, bins, log, omega_min, plateau):
    """Per-file D(omega) on common edges, D0 and omega*; their means and standard errors."""
    from parjam import observables

    kinds = {s["attrs"]["matrix"] for s in specs}
    if len(kinds) != 1:
        raise ParjamError(f"spectrum files mix matrices {sorted(kinds)}: average one kind")
    omegas = [s["frequency"][s["frequency"] > 0] for s in specs]
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
    from parjam.commands.modes import parse_pair

    PETSc = env.petsc()
    rank = PETSc.COMM_WORLD.getRank()
    if args.bins < 1:
        raise ParjamError(f"--bins must be >= 1, got {args.bins}")
    plateau = parse_pair(args.plateau, "--plateau") if args.plateau else None
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
