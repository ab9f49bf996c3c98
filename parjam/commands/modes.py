"""``parjam modes``: spectra of a packing's dynamical matrices (docs/howto/spectra.md)."""

import os
import sys

import numpy as np

from parjam import units
from parjam.commands import parse_pair
from parjam.errors import ParjamError
from parjam.vib.solver_choice import MATRICES, METHODS, check_tol

EXIT_INCOMPLETE = 4  # some requested pairs did not converge to the tolerance
MAX_BINS = 1_000_000  # bins cost memory linearly; 1e6 is finer than any spectrum needs
#: --k: the shift-and-invert basis holds ~2k vectors of d N' numbers; beyond 1e5 pairs a window
#: (slicing) or the dense solver is the right tool, and the file also checks k <= d N' - d
MAX_K = 100_000


def add_parser(sub):
    p = sub.add_parser(
        "modes", help="lowest modes or all modes in a frequency window of D, M or M'",
        description="Eigenvalues lambda = omega^2 of the dynamical matrix of Eq. (1) restricted "
        "to the non-rattlers, the d translations deflated: the full matrix D = M + M', the "
        "relaxed-spring matrix M or the stress term M'. Per mode: residual, participation ratio, "
        "transverse and longitudinal sums; D(omega) per mode with D0 and omega*. SLEPc objects "
        "take options with the prefix modes_ (-modes_eps_view, -modes_st_mat_mumps_icntl_7 5).")
    p.add_argument("packing", help="packing file (H5MD, from parjam pack)")
    p.add_argument("--matrix", nargs="+", default=["full"], choices=MATRICES,
                   help="one or more matrices (default full); several give one file each, "
                   "OUT with .MATRIX before .h5, e.g. --matrix full relaxed for Fig. 'compare'")
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--k", type=int, help="number of lowest non-translational modes")
    g.add_argument("--window", help="frequency window WA,WB [tau^-1]: every mode with WA <= "
                   "omega <= WB (method auto: dense LAPACK up to 3000 degrees of freedom, "
                   "spectrum slicing above)")
    p.add_argument("--method", default="auto", choices=METHODS,
                   help="auto: --window: dense LAPACK up to 3000 dof, else slice; --k: "
                   "sinvert, or dense up to 3000 dof when N is tiny (<= 400 dof), k >= 15%% of "
                   "the modes or --tol < 1e-12 (measured crossovers, "
                   "docs/results/speed-accuracy.md)")
    p.add_argument("--vectors", action="store_true", help="store the eigenvectors (K, N', d)")
    p.add_argument("--tol", type=float, default=1e-10,
                   help="accept pairs with ||D v - lambda v|| / ||D||_inf <= TOL (1e-10; "
                   "from 1e-15, the round-off, to 1e-2)")
    p.add_argument("--target", type=float,
                   help="sinvert target (default -1e-9 ||D||_inf, just below the zero cluster)")
    p.add_argument("--bins", type=int, help="D(omega) bins (default: about the square root of "
                   "the number of modes computed, 3 to 40)")
    p.add_argument("--log-bins", action="store_true", help="logarithmic D(omega) bins")
    p.add_argument("--omega-min", type=float, help="lowest edge of log bins [tau^-1]")
    p.add_argument("--plateau", help="plateau window W1,W2 [tau^-1] for D0 and omega* (default: "
                   "the 30 %% and 60 %% frequency quantiles of a complete spectrum, "
                   "[omega_k / 2, omega_k] of the k lowest modes)")
    p.add_argument("--out", required=True, help="spectrum file to write (.h5)")
    p.add_argument("--plot", help="PNG of D(omega), eps_perp/eps_par and participation")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    p.set_defaults(run=run, reads=lambda a: [a.packing])


def output_paths(out, matrices):
    if len(matrices) == 1:
        return {matrices[0]: out}
    stem, ext = os.path.splitext(out)
    return {m: f"{stem}.{m}{ext or '.h5'}" for m in matrices}


def validate(args):
    if len(set(args.matrix)) != len(args.matrix):
        raise ParjamError("--matrix lists a matrix twice")
    if args.k is not None and args.k < 1:
        raise ParjamError(f"--k must be >= 1, got {args.k}")
    if args.k is not None and args.k > MAX_K:
        raise ParjamError(f"--k must be <= {MAX_K} (k eigenvectors of d N' numbers each; more "
                          f"modes: --window or dense), got {args.k}")
    args.window_pair = parse_pair(args.window, "--window") if args.window else None
    args.plateau_pair = parse_pair(args.plateau, "--plateau") if args.plateau else None
    if args.bins is not None and not 1 <= args.bins <= MAX_BINS:
        raise ParjamError(f"--bins must lie in [1, {MAX_BINS}], got {args.bins}")
    if args.target is not None and not np.isfinite(args.target):
        raise ParjamError("--target must be finite")
    if args.method == "slice" and args.window is None:
        raise ParjamError("--method slice needs --window WA,WB")
    check_tol(args.tol)


def option_conflicts(args):
    """One-line warnings for PETSc options that contradict the command line: -modes_eps_nev
    sets SLEPc's number of pairs after --k did (it used to end in exit 4 without a word), and
    -modes_eps_interval the slicing interval after --window did."""
    from parjam import env

    opts = env.petsc().Options()
    out = []
    if args.k is not None and opts.hasName("modes_eps_nev"):
        nev = opts.getString("modes_eps_nev")
        if nev != str(args.k):
            out.append(f"-modes_eps_nev {nev} contradicts --k {args.k}: shift-and-invert may "
                       f"then stop after {nev} pairs and report the others missing (exit 4), "
                       f"the dense solver ignores it; --k alone sets the number of modes")
    if args.window is not None and opts.hasName("modes_eps_interval"):
        out.append(f"-modes_eps_interval {opts.getString('modes_eps_interval')} overrides the "
                   f"slicing interval of --window {args.window} (the dense solver ignores it); "
                   f"--window alone sets it")
    return out


def summary_line(kind, spec, dos):
    w = spec.frequency
    rng = f"omega {w[0]:.4g} .. {w[-1]:.4g} {units.text('frequency')}" if len(w) else "no modes"
    extra = (f", D0 = {dos['D0']:.4g} {units.text('dos')}, omega* = {dos['omega_star']:.4g} "
             f"{units.text('frequency')}" if dos else "")
    return (f"{kind}: {len(w)} modes by {spec.method} ({rng}), max residual "
            f"{spec.error.max() if len(w) else 0:.1e}, {spec.seconds:.2f} s{extra}")


def run(args):
    # the work's modules load here, not when the command line is built (parjam --help)
    from parjam import env
    from parjam.files import h5md, outputs, rowio
    from parjam.net import active
    from parjam.progress import Progress
    from parjam.vib import spectrum

    PETSc = env.petsc()
    comm = PETSc.COMM_WORLD
    rank = comm.getRank()
    validate(args)
    outputs.check(comm, files=[("--out", p) for p in output_paths(args.out, args.matrix).values()]
                  + [("--plot", args.plot)], inputs=[args.packing])
    for line in option_conflicts(args):
        if rank == 0:
            print(f"parjam: warning: {line}", file=sys.stderr, flush=True)
    progress = Progress(comm.tompi4py(), args.quiet, "modes: ")
    # this rank's rows of the file only (parjam.files.rowio), kept for the output's /particles/all
    rows = rowio.read_rows(comm, args.packing)
    system = spectrum.distributed_system(active.from_rows(comm, rows))
    progress(f"N' = {system.n} non-rattlers ({system.n_rattlers} rattlers), "
             f"{system.n_contacts} contacts, d = {system.d}")
    prov = h5md.provenance(comm.getSize(), {"command": "modes"})
    paths = output_paths(args.out, args.matrix)
    code = 0
    written = {}
    for kind in args.matrix:
        spec = spectrum.compute(comm, system, kind, k=args.k, window=args.window_pair,
                                method=args.method, tol=args.tol, target=args.target,
                                vectors=args.vectors, progress=progress)
        dos = dos_or_none(spec, system, args)
        write(comm, paths[kind], spec, system, rows, dos, prov)  # collective, by row blocks
        if rank == 0:
            print(summary_line(kind, spec, dos), flush=True)
            report_problems(kind, spec)
        written[kind] = paths[kind]
        if not spec.complete:
            code = EXIT_INCOMPLETE
    if args.plot:
        def draw():
            from parjam.files import modes_io
            from parjam.plot import spectra as plot_spectra

            with outputs.atomic_path(args.plot, ".png") as tmp:
                plot_spectra.spectra_figure([modes_io.read_spectrum(p) for p in written.values()],
                                            tmp)

        outputs.on_root(comm, draw)
    return code


def dos_or_none(spec, system, args):
    from parjam.vib import observables

    if not np.any(spec.physical):  # zero modes (floppy) are no vibrations: not in D(omega)
        return None
    dos = observables.dos_record(spec.frequency[spec.physical], system.n_modes, args.bins,
                              args.log_bins, args.omega_min, args.plateau_pair)
    return flag_undefined(dos, spec.matrix)


def flag_undefined(dos, kind):
    """NaN is never stored silently: D0 = 0 or omega* = NaN (a plateau window without modes, or
    a partial spectrum that never reaches D0/2) is named in /dos attrs ``undefined`` and said on
    stderr; D0 and omega* are then stored as NaN with that flag."""
    bad = [key for key in ("D0", "omega_star") if not (np.isfinite(dos[key]) and dos[key] > 0)]
    dos["undefined"] = ",".join(bad)
    if bad:
        dos.update({key: float("nan") for key in bad})
        w1, w2 = dos["plateau_window"]
        print(f"parjam: warning: {kind}: {' and '.join(bad)} undefined: the plateau window "
              f"{w1:.4g},{w2:.4g} holds no mode (stored as NaN, flagged in /dos attrs "
              f"'undefined'); choose --plateau inside the computed frequencies",
              file=sys.stderr, flush=True)
    return dos


def write(comm, path, spec, system, rows, dos, prov):
    empty = {"omega": np.zeros(0), "edges": np.zeros(0), "density": np.zeros(0),
             "note": "no positive frequency"}
    from parjam.files import modes_io

    modes_io.write_spectrum(comm, path, spec, system, rows, dos or empty, prov)


def report_problems(kind, spec):
    if len(spec.rejected_eigenvalue) or spec.n_missing > 0:
        print(f"parjam: warning: {kind}: only {len(spec.eigenvalue)} of {spec.n_requested} "
              f"pairs reached residual <= {spec.tolerance:g}; {len(spec.rejected_eigenvalue)} "
              f"rejected (stored under /modes/rejected), "
              f"{max(spec.n_missing - len(spec.rejected_eigenvalue), 0)} not converged",
              file=sys.stderr, flush=True)
    if spec.n_zero and kind != "stress":
        print(f"parjam: warning: {kind}: {spec.n_zero} zero mode(s) (|lambda| <= "
              f"{spec.zero_tol:.1e}) beyond the deflated translations: a floppy "
              f"(hypostatic) network; they are counted in /modes n_zero_modes and left out of "
              f"D(omega)", file=sys.stderr, flush=True)
    if spec.unstable:
        print(f"parjam: warning: {kind}: unstable packing: {spec.n_negative} eigenvalue(s) "
              f"below -{spec.zero_tol:.1e} (beyond round-off)", file=sys.stderr, flush=True)
