"""``parjam dos``: ensemble-averaged D(omega), D0 and omega* over spectrum files."""

import sys

import numpy as np

from parjam import units
from parjam.commands import parse_pair
from parjam.errors import ParjamError
from parjam.vib.solver_choice import MATRICES


def add_parser(sub):
    p = sub.add_parser(
        "dos", help="ensemble-averaged density of states over spectrum files",
        description="D(omega) per mode of each spectrum file (from parjam modes) on common bins "
        "up to the lowest of the files' highest computed frequencies, averaged with standard "
        "errors; D0 and omega* per file (definitions in docs/explanation/physics.md) and their "
        "means.")
    p.add_argument("spectra", nargs="+", help="spectrum files of one matrix kind (with --method "
                   "kpm: packing files)")
    p.add_argument("--bins", type=int, default=40, help="number of bins (40)")
    p.add_argument("--log-bins", action="store_true", help="logarithmic bins")
    p.add_argument("--omega-min", type=float, help="lowest edge of log bins")
    p.add_argument("--plateau", help="plateau window W1,W2 for D0 and omega*")
    p.add_argument("--out", required=True, help="HDF5 file for the averaged D(omega)")
    p.add_argument("--plot", help="PNG of the averaged D(omega) with error bars")
    k = p.add_argument_group("stochastic D(omega) of packings (--method kpm, "
                             "docs/results/speed-accuracy.md)")
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
    p.add_argument("-q", "--quiet", action="store_true", help="no summary line (warnings and errors still)")
    p.set_defaults(run=run, reads=lambda a: a.spectra)


MAX_BINS = 1_000_000  # bins cost memory and time linearly; 1e6 is finer than any spectrum needs
#: KPM sizes: the Jackson kernel resolves ~pi (b - a) / M of the band [a, b]; 2^16 moments
#: resolve 5e-5 of it, finer than the level spacing of any packing parjam handles up to
#: N ~ 10^4 and than any useful bin, and cost M/2 matrix products per probe
MAX_MOMENTS = 65_536
#: the stochastic trace error falls as 1/sqrt(probes x d N'): 10^4 probes give 1 % on a single
#: mode's weight; more only multiply the time
MAX_PROBES = 10_000


def check_sizes(args):
    """Every size a user can ask of dos, bounded (with the reason above), before any work."""
    if not 1 <= args.bins <= MAX_BINS:
        raise ParjamError(f"--bins must lie in [1, {MAX_BINS}], got {args.bins}")
    if getattr(args, "method", "spectra") != "kpm":
        return
    if not 2 <= args.moments <= MAX_MOMENTS:
        raise ParjamError(f"--moments must lie in [2, {MAX_MOMENTS}] (2^16 moments already "
                          f"resolve 5e-5 of the spectral band), got {args.moments}")
    if not 1 <= args.probes <= MAX_PROBES:
        raise ParjamError(f"--probes must lie in [1, {MAX_PROBES}] (the stochastic error falls "
                          f"only as 1/sqrt(probes)), got {args.probes}")


def check_duplicates(paths):
    """The same file twice (by path, link or identical content) would fake an ensemble with a
    zero error bar."""
    from parjam.files import h5md, outputs

    digests = {}
    for k, path in enumerate(paths):
        for other in paths[:k]:
            if outputs.same_file(path, other):
                raise ParjamError(f"{path} and {other} are the same file: each input must be "
                                  f"a different member")
        try:
            digest = h5md.sha256(path)
        except OSError:
            continue  # unreadable: the reader says why
        if digest in digests:
            raise ParjamError(f"{path} and {digests[digest]} have identical contents: each "
                              f"input must be a different member")
        digests[digest] = path


def check_same_system(described):
    """``described``: (path, d, N, packing sha256 or "") per input.  Refuse mixed dimensions, mixed
    N and two spectra of one packing."""
    first = described[0]
    seen = {}
    for path, d, n, sha in described:
        if d != first[1]:
            raise ParjamError(f"{path} is {d}D but {first[0]} is {first[1]}D: average one "
                              f"dimension")
        if n != first[2]:
            raise ParjamError(f"{path} has N = {n} but {first[0]} has N = {first[2]}: average "
                              f"one system size")
        if sha and sha in seen:
            raise ParjamError(f"{path} and {seen[sha]} are spectra of the same packing: each "
                              f"input must be a different member")
        seen[sha] = path


def check_defined(paths, d0s, stars, plateau):
    """NaN is never stored silently: D0 and omega* must be defined for every input."""
    for path, d0, ws in zip(paths, d0s, stars):
        if not (np.isfinite(d0) and d0 > 0 and np.isfinite(ws)):
            where = (f"the plateau window --plateau {plateau[0]:g},{plateau[1]:g}" if plateau
                     else "the default plateau window")
            raise ParjamError(f"{path}: {where} holds no mode (D0 = {d0:.3g}): omega* is "
                              f"undefined; choose a window inside the computed frequencies")


def ensemble_state(specs):
    """What the figure names the ensemble by: N, d and the states of its spectra (their
    packings' labels, e.g. dphi1.0e-04; several joined by commas)."""
    a = specs[0]["attrs"]
    states = sorted({str(s["attrs"].get("state", "")) for s in specs} - {""})
    if not states:  # packings without a state label: their mean pressure names them
        states = [f"p{np.mean([float(s['attrs'].get('pressure', np.nan)) for s in specs]):.1e}"]
    return {"n": int(a.get("n_active", 0)) + int(a.get("n_rattlers", 0)),
            "dimension": int(a.get("dimension", 0)), "state": ",".join(states)}


def ensemble(specs, bins, log, omega_min, plateau):
    """Per-file D(omega) on common edges, D0 and omega*; their means and standard errors."""
    from parjam.vib import observables

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
    from parjam import env
    from parjam.files import h5md, modes_io, outputs
    from parjam.vib import observables

    PETSc = env.petsc()
    check_sizes(args)
    plateau = parse_pair(args.plateau, "--plateau") if args.plateau else None
    outputs.check(PETSc.COMM_WORLD, files=[("--out", args.out), ("--plot", args.plot)],
                  inputs=args.spectra)
    check_duplicates(args.spectra)
    if getattr(args, "method", "spectra") == "kpm":
        return run_kpm(args, plateau)
    specs = [modes_io.read_spectrum(p) for p in args.spectra]
    check_same_system([(p, int(s["attrs"].get("dimension", 0)),
                        int(s["attrs"].get("n_active", 0)) + int(s["attrs"].get("n_rattlers", 0)),
                        str(s["attrs"].get("packing_sha256", ""))) for p, s in
                       zip(args.spectra, specs)])
    res = ensemble(specs, args.bins, args.log_bins, args.omega_min, plateau)
    check_defined(args.spectra, res["D0_each"], res["omega_star_each"], plateau)
    d0, d0_err = observables.ensemble_mean(res["D0_each"][:, None])
    ws, ws_err = observables.ensemble_mean(res["omega_star_each"][:, None])
    dos = {"omega": res["omega"], "edges": res["edges"], "density": res["density"],
           "density_error": res["density_error"], "binning": "log" if args.log_bins else "linear",
           "normalisation": "per mode: counts / ((d N' - d) * bin width), then averaged",
           "matrix": res["matrix"], "n_files": len(specs), "D0": float(d0[0]),
           "D0_error": float(d0_err[0]), "omega_star": float(ws[0]),
           "omega_star_error": float(ws_err[0]), "D0_each": res["D0_each"],
           "omega_star_each": res["omega_star_each"], **ensemble_state(specs)}
    prov = h5md.provenance(PETSc.COMM_WORLD.getSize(), {"command": "dos", "files": args.spectra})
    outputs.on_root(PETSc.COMM_WORLD, lambda: write(args, dos, prov, (
        f"{res['matrix']}: {len(specs)} spectra, D0 = {d0[0]:.4g} +- {d0_err[0]:.2g} "
        f"{units.text('dos')}, omega* = {ws[0]:.4g} +- {ws_err[0]:.2g} "
        f"{units.text('frequency')}")))
    return 0


def write(args, dos, prov, line):
    """Rank 0: the D(omega) file, the summary line and the figure (policy: parjam.files.outputs)."""
    from parjam.files import h5md, modes_io, outputs

    with h5md.atomic_h5(args.out) as f:
        h5md.write_h5md_header(f, prov)
        modes_io.write_dos(f, dos)
    if not getattr(args, "quiet", False):
        print(line, flush=True)
    if args.plot:
        from parjam.plot.spectra import ensemble_dos_figure

        with outputs.atomic_path(args.plot, ".png") as tmp:
            ensemble_dos_figure(dos["omega"], dos["density"], dos["density_error"], tmp,
                                dos["matrix"], dos["omega_star"], dos_heading(dos))


def dos_heading(dos):
    """The figure's title: N, d, the state and the number of members averaged."""
    from parjam.plot.labels import title

    what = rf"$D(\omega)$ of the {dos['matrix']} matrix"
    what += ", KPM" if dos.get("method") == "kpm" else ""
    return title(dos.get("n"), dos.get("dimension"), dos.get("state"), dos.get("n_files"), what)


def kpm_ensemble(comm, paths, args, plateau, progress):
    """KPM D(omega) of each packing on common bins (up to the lowest upper bound of the files),
    D0 and omega* each; mean and standard error over files (over probes for one file)."""
    from parjam.files import rowio
    from parjam.net import active
    from parjam.vib import kpm, observables, spectrum

    bounds = parse_pair(args.kpm_bounds, "--kpm-bounds") if args.kpm_bounds else None
    rows = [rowio.read_rows(comm, path) for path in paths]  # all checked before any work
    check_same_system([(p, k.d, k.n, "") for p, k in zip(paths, rows)])
    results = []
    for path, part in zip(paths, rows):  # this rank's rows only (parjam.net.active)
        system = spectrum.distributed_system(active.from_rows(comm, part))
        progress(f"{path}: N' = {system.n}, {system.n_contacts} contacts")
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
    from parjam import env
    from parjam.files import h5md, outputs
    from parjam.vib import observables
    from parjam.progress import Progress

    PETSc = env.petsc()
    comm = PETSc.COMM_WORLD
    progress = Progress(comm.tompi4py(), False, "dos: ")
    results, edges, mean, err, d0s, stars = kpm_ensemble(comm, args.spectra, args, plateau,
                                                         progress)
    check_defined(args.spectra, d0s, stars, plateau)
    d0, d0_err = observables.ensemble_mean(d0s[:, None])
    ws, ws_err = observables.ensemble_mean(stars[:, None])
    for path, r in zip(args.spectra, results if comm.getRank() == 0 else []):
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
    prov = h5md.provenance(comm.getSize(), {"command": "dos", "files": args.spectra})
    outputs.on_root(comm, lambda: write(args, dos, prov, (
        f"{args.matrix}: KPM ({args.moments} moments x {args.probes} probes) of "
        f"{len(results)} packings, D0 = {d0[0]:.4g} +- {d0_err[0]:.2g} {units.text('dos')}, "
        f"omega* = {ws[0]:.4g} +- {ws_err[0]:.2g} {units.text('frequency')}, "
        f"{sum(r.seconds for r in results):.2f} s")))
    return 0
