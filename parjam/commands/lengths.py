"""``parjam lengths``: sound speeds c_L, c_T, the lengths l_L = c_L / omega*, l_T = c_T / omega*
and l* (cut cubes), and the longitudinal/transverse structure factors of the eigenmodes
(see parjam.lengths and parjam.vib.structure).  Computes only what ``--what`` asks for."""

import os

import numpy as np

from parjam.errors import ParjamError


def add_parser(sub):
    p = sub.add_parser(
        "lengths", help="sound speeds, l_L, l_T, l* and the structure factors F_L, F_T",
        description="speeds: B and G by linear response (parjam moduli) and c_L = sqrt((B + "
        "2(d-1)G/d)/rho), c_T = sqrt(G/rho) with rho = N'/V (non-rattlers, unit masses). omega: "
        "the spectrum (dense when complete, else --k lowest modes) and omega*; with speeds also "
        "l_L = c_L/omega*, l_T = c_T/omega*. lstar: cubes of several edges with their boundary "
        "contacts cut, the cut-plane count and the exact non-trivial soft modes (MUMPS "
        "inertia) and extended soft modes (dense) of each; l* where the count changes sign and "
        "where extended soft modes disappear, against the Maxwell estimate d z <|r_a|> / dz. structure: F_L(k, omega), F_T(k, omega) of the eigenmodes on the box "
        "wavevectors, peak dispersion, its slopes and l_T = 1/k* where the transverse peak "
        "reaches omega*.")
    p.add_argument("packing", help="packing file (H5MD, from parjam pack)")
    p.add_argument("--what", nargs="+", default=["speeds", "omega"],
                   help="any of speeds, omega, lstar, structure, all (default: speeds omega)")
    p.add_argument("--matrix", default="full", choices=("full", "relaxed"),
                   help="dynamical matrix for omega* and the structure factors (default full)")
    p.add_argument("--k", type=int, help="lowest modes to compute (default: all, by dense "
                   "LAPACK, when d N' <= 12000)")
    p.add_argument("--method", default="auto", choices=("auto", "dense", "sinvert"))
    p.add_argument("--plateau", help="plateau window W1,W2 for D0 and omega*")
    p.add_argument("--edges", help="cube edges for l*, as fractions of L (default "
                   "0.2,0.3,...,1.0)")
    p.add_argument("--samples", type=int, default=8, help="cube positions per edge (default 8)")
    p.add_argument("--seed", type=int, default=0, help="seed of the cube positions")
    p.add_argument("--e0", type=float, help="extension threshold of the cubes' extended soft "
                   "modes (default 0.4 x 2^-d)")
    p.add_argument("--kmax", type=float, help="largest wavenumber (default pi / <sigma>)")
    p.add_argument("--kfit", type=float,
                   help="fit omega = c k over k <= KFIT (default 3 pi/L: shells |m|^2 = 1, 2)")
    p.add_argument("--smooth", type=float, default=0.05,
                   help="relative width of the peak smoothing in log omega (default 0.05)")
    p.add_argument("--out", help="write /lengths/* to this HDF5 file")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    p.set_defaults(run=run, reads=lambda a: [a.packing])


MAX_SAMPLES = 10_000
MAX_K = 100_000  # as parjam modes: beyond 1e5 lowest pairs use the dense solver
#: --kmax: the structure factors take a phase exp(i k.r) per box wavevector of the grid
#: |m| <= kmax L / (2 pi), (2 m + 1)^d points, and particle: 1e8 of them (1.6 GB of complex
#: numbers) is far beyond the few shells up to ~pi / sigma that the dispersion and l_T need
MAX_PHASES = 100_000_000


def check_kmax(kmax, rows):
    """Bound the work of --kmax before anything is allocated (the box is known only now;
    ``rows``: a packing or this rank's rowio.Rows, anything with n, d and L)."""
    if kmax is None:
        return
    m = np.floor(kmax * rows.L / (2.0 * np.pi))
    log_phases = rows.d * np.log10(2.0 * m + 1.0) + np.log10(rows.n)  # no overflow warning
    if not log_phases <= np.log10(MAX_PHASES):
        raise ParjamError(f"--kmax {kmax:g} spans {2 * m + 1:.3g}^{rows.d} box wavevectors x "
                          f"{rows.n} particles (more than {MAX_PHASES:.0e} phases); the "
                          f"structure factors need k up to a few pi / sigma: lower --kmax")


def parse_floats(text, name, count=None):
    try:
        vals = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ParjamError(f"{name} {text!r}: expected comma-separated numbers") from None
    if not vals or (count and len(vals) != count) or not all(np.isfinite(vals)):
        raise ParjamError(f"{name} {text!r}: expected {count or 'some'} finite numbers")
    return vals


def validate(args):
    from parjam.lengths import WHAT

    what = list(WHAT) if "all" in args.what else args.what
    bad = [w for w in what if w not in WHAT]
    if bad:
        raise ParjamError(f"--what {' '.join(bad)}: choose from {', '.join(WHAT)} or all")
    if args.k is not None and not 1 <= args.k <= MAX_K:
        raise ParjamError(f"--k must lie in [1, {MAX_K}] (k eigenvectors of d N' numbers "
                          f"each), got {args.k}")
    if not 1 <= args.samples <= MAX_SAMPLES:
        raise ParjamError(f"--samples must lie in [1, {MAX_SAMPLES}] (each cube costs a "
                          f"factorisation; 1e4 positions per edge already give 1 % counts), "
                          f"got {args.samples}")
    if not 0 < args.smooth < 1:
        raise ParjamError(f"--smooth must lie in (0, 1), got {args.smooth}")
    edges = parse_floats(args.edges, "--edges") if args.edges else None
    if edges and not all(0 < e <= 1 for e in edges):
        raise ParjamError(f"--edges must be fractions of L in (0, 1], got {args.edges}")
    plateau = tuple(parse_floats(args.plateau, "--plateau", 2)) if args.plateau else None
    if args.e0 is not None and not 0 < args.e0 < 1:
        raise ParjamError(f"--e0 must lie in (0, 1), got {args.e0}")
    for name in ("kmax", "kfit"):
        v = getattr(args, name)
        if v is not None and not v > 0:
            raise ParjamError(f"--{name} must be positive, got {v}")
    return what, edges, plateau


def run(args):
    from parjam import env, lengths
    from parjam.files import h5md, outputs, rowio
    from parjam.files import lengths as lengths_file
    from parjam.progress import Progress

    PETSc = env.petsc()
    comm = PETSc.COMM_WORLD
    what, edges, plateau = validate(args)
    outputs.check(comm, files=[("--out", args.out)], inputs=[args.packing])
    progress = Progress(comm, args.quiet, "lengths: ")
    rows = rowio.read_rows(comm, args.packing)  # this rank's rows only (parjam.files.rowio)
    check_kmax(args.kmax, rows)
    res = lengths.compute(
        comm, rows, what, matrix=args.matrix, k=args.k, method=args.method, plateau=plateau,
        ells=None if edges is None else np.array(edges) * rows.L, samples=args.samples,
        seed=args.seed, k_max=args.kmax, k_fit=args.kfit, smooth=args.smooth,
        progress=progress, e0=args.e0)
    if args.out:
        prov = h5md.provenance(comm.getSize(), {
            "command": "lengths", "input": os.path.abspath(args.packing),
            "input_sha256": h5md.sha256(args.packing), "what": what})
        outputs.on_root(comm, lambda: lengths_file.write(args.out, res, prov))
    if comm.getRank() == 0:
        print_summary(res, args.out)
    return 0


def print_summary(res, out):
    """The results, each with its reduced unit (parjam.units)."""
    from parjam import units

    s = res.summary()
    d = s.get("d", "d")
    u = {q: units.text(q, d) for q in ("modulus", "speed", "dos", "frequency", "length",
                                       "density", "wavenumber")}
    lines = [f"N' / N            {s['N_active']} / {s['N']}   (rho = N'/V = {s['rho']:.6g} "
             f"{u['density']})",
             f"z, dz             {s['z']:.4f}, {s['dz']:.4f}"]
    if "B" in s:
        lines += [f"B, G              {s['B']:.6e}, {s['G']:.6e} {u['modulus']}"
                  + ("   (G_min < 0: UNSTABLE to some shear)" if s["G_min"] < 0 else ""),
                  f"c_L, c_T          {s['c_L']:.6e}, {s['c_T']:.6e} {u['speed']}"]
    if "omega_star" in s:
        lines.append(f"D0, omega*        {s['D0']:.6e} {u['dos']}, {s['omega_star']:.6e} "
                     f"{u['frequency']}   ({res.spectrum.matrix} matrix, "
                     f"{len(res.spectrum.eigenvalue)} modes)")
    if "l_L" in s:
        lines.append(f"l_L, l_T          {s['l_L']:.6e}, {s['l_T']:.6e} {u['length']}")
    if "lstar" in s:
        missing = [name for key, name in (("lstar", "the count"),
                                          ("lstar_extended", "the extended soft modes"))
                   if not np.isfinite(s[key])]
        note = (f"; NaN: {' and '.join(missing)} did not change within the edges tried "
                f"(--edges)" if missing else "")
        lines.append(f"l* (cut cubes)    {s['lstar']:.4g} from the count, "
                     f"{s['lstar_extended']:.4g} from the extended soft modes {u['length']}   "
                     f"(estimate d z <|r_a|>/dz = {s['lstar_estimate']:.4g}; L = {s['L']:.4g}"
                     f"{note})")
        if res.lstar.failed:
            lines.append(f"                  {res.lstar.failed} cubes without a clear gap "
                         "left out of the soft-mode counts")
    if "c_T_fit" in s:
        lines.append(f"dispersion slopes c_L, c_T = {s['c_L_fit']:.6e}, {s['c_T_fit']:.6e} "
                     f"{u['speed']}   (k <= {s['k_fit']:.3g} {u['wavenumber']})")
        if "l_T_structure" in s:
            lines.append(f"l_T, l_L from F   {s['l_T_structure']:.6e}, {s['l_L_structure']:.6e}"
                         f" {u['length']}   (1/k where the peak reaches omega*)")
    if out:
        lines.append(f"written           {out}")
    print("\n".join(lines), flush=True)
