"""``parjam softmodes``: soft modes of an isostatic packing after plane cuts (Sections II-III and
the Appendix of Wyart et al. 2005): null-space count and basis, extension, f(x), trial modes."""

import os

import numpy as np

from parjam.errors import ParjamError
from parjam.softmodes import COLUMNS_DEFAULT, COLUMNS_MAX, check_directory


def add_parser(sub):
    p = sub.add_parser(
        "softmodes", help="soft modes after cutting the contacts that cross planes",
        description="Remove rattlers, cut every contact whose bond crosses the given planes, and "
        "find the null space of the rigidity matrix of the rest (MUMPS inertia count, basis "
        "orthogonal to the d translations by block inverse iteration or SLEPc). Reports the count against "
        "d + q - 1, trivially localised modes, the extension of each mode, the overlap function "
        "f(x), the extended subspace q'/q and the trial-mode energies against Eq. (kkk). "
        "PETSc/SLEPc options: -soft_ksp_* -soft_pc_* and -soft_gap_eps_* (block basis), "
        "-soft_eps_* -soft_st_* (krylov basis), -soft_inertia_* (counts).")
    p.add_argument("packing", help="packing file (H5MD, from parjam pack)")
    p.add_argument("--cut", action="append", default=[], metavar="AXIS=FRACTION",
                   help="cut the plane AXIS = FRACTION * L (e.g. x=0.5; x=0 cuts the bonds that "
                   "wrap across the box edge); repeat for several planes")
    p.add_argument("--subdivide", type=int, metavar="M",
                   help="also cut the planes k L / M (k = 0..M-1) in every direction: M^d "
                   "sub-boxes (Section III)")
    p.add_argument("--e0", type=float, default=0.1,
                   help="extension threshold of the extended subspace and of Eq. (kkk) (0.1)")
    p.add_argument("--bins", type=int, default=10, help="slabs of the box for f(x) (10)")
    p.add_argument("--basis", choices=["block", "krylov"], default="block",
                   help="null-space method: block inverse iteration with one MUMPS factor "
                   "(block, default) or SLEPc Krylov-Schur shift-and-invert (krylov)")
    p.add_argument("--columns", type=int, default=COLUMNS_DEFAULT, metavar="K",
                   help="block basis: find the null vectors K columns at a time, so a cut holds "
                   "one copy of the basis plus O(N K) work arrays instead of several N x q ones "
                   f"(1..{COLUMNS_MAX}; K above the null-space dimension is the single-block "
                   "method)")
    p.add_argument("--scratch", metavar="DIR",
                   help="block basis: keep the basis out of core, each rank's rows in a file "
                   "of a temporary directory under DIR (removed at the end, also on error), "
                   "read back in column blocks and row chunks; for cuts whose basis "
                   "(N d n_soft 8 bytes) does not fit in memory (default: in memory)")
    p.add_argument("--vectors", action="store_true",
                   help="also store the basis (/softmodes/basis, modes x N x d)")
    p.add_argument("--allow-hyperstatic", action="store_true",
                   help="analyse a packing that is not isostatic (Nc != Nc_iso) anyway")
    p.add_argument("--out", required=True, help="output HDF5 file")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    p.set_defaults(run=run, reads=lambda a: [a.packing])


def validate(args):
    if not (np.isfinite(args.e0) and 0.0 < args.e0 < 1.0):
        raise ParjamError(f"--e0 must lie in (0, 1), got {args.e0}")
    if not (2 <= args.bins <= 100_000):
        raise ParjamError(f"--bins must lie in [2, 100000], got {args.bins}")
    if args.subdivide is not None and not (1 <= args.subdivide <= 1000):
        raise ParjamError(f"--subdivide must lie in [1, 1000], got {args.subdivide}")
    if not (1 <= args.columns <= COLUMNS_MAX):
        raise ParjamError(f"--columns must lie in [1, {COLUMNS_MAX}], got {args.columns}")
    if args.scratch is not None:
        if args.basis != "block":
            raise ParjamError("--scratch needs --basis block")
        check_directory(args.scratch)
    if not args.cut and args.subdivide is None:
        raise ParjamError("no cut given: use --cut AXIS=FRACTION (e.g. --cut x=0.5) and/or "
                          "--subdivide M")


def planes_from(args, d):
    from parjam import softmodes as sm

    planes = [sm.parse_cut(text, d) for text in args.cut]
    if args.subdivide is not None:
        planes += sm.subdivision_planes(args.subdivide, d)
    return list(dict.fromkeys(planes))  # unique, in the order given


def peak_rss_mb(comm):
    """Largest resident set size over the ranks so far (MB)."""
    import resource

    from mpi4py import MPI

    mine = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # kB on Linux
    return float(comm.tompi4py().allreduce(mine, op=MPI.MAX))


def run(args):
    validate(args)
    from parjam import env, softmodes as sm
    from parjam.files import h5md, outputs, rowio
    from parjam.net import active
    from parjam.progress import Progress

    PETSc = env.petsc()
    comm = PETSc.COMM_WORLD
    progress = Progress(comm, args.quiet, "softmodes: ")
    outputs.check(comm, files=[("--out", args.out)], inputs=[args.packing])
    rows = rowio.read_rows(comm, args.packing)  # this rank's rows only, validated
    planes = planes_from(args, rows.d)
    net = active.from_rows(comm, rows)  # the distributed active network
    cs = sm.prepare(None, planes, args.allow_hyperstatic, net=net)
    progress(f"N' = {cs.n} non-rattlers, Nc = {cs.n_contacts} ({cs.excess:+d} from "
             f"isostatic), q = {cs.q} cut contacts on {len(cs.planes)} plane(s)")
    with sm.scratch_space(comm, args.scratch) as scratch:  # the basis on disk lives in here
        res = sm.analyze(comm, cs, args.e0, args.bins, progress, args.basis, args.columns,
                         scratch)
        res.solver["peak_rss_mb"] = peak_rss_mb(comm)
        prov = h5md.provenance(comm.getSize(), {
            "command": "softmodes", "input": os.path.abspath(args.packing),
            "input_sha256": h5md.sha256(args.packing) if comm.getRank() == 0 else "",
            "planes": [p.label for p in cs.planes], "e0": args.e0, "bins": args.bins,
            "basis": args.basis, "columns": args.columns,
            "out_of_core": args.scratch is not None,
            "allow_hyperstatic": bool(args.allow_hyperstatic)})
        write(comm, args.out, res, args.vectors, prov)
    if comm.getRank() == 0:
        print_summary(res, args.out)
    return 0


def write(comm, path, res, vectors, prov):
    """The file (parjam.files.softmodes) gets each rank's rows on rank 0 in turn, which writes; a
    failed write there is then told to every rank (one line everywhere, no abort)."""
    from parjam import softmodes as sm
    from parjam.files import softmodes as soft_file

    cut, localised = sm.cut_pairs(res.cs), sm.localised_ids(res.cs)  # collective
    message = None
    try:
        soft_file.write(comm, path, res, cut, localised, vectors, prov)
    except ParjamError as exc:
        message = str(exc)
    message = comm.tompi4py().bcast(message, root=0)
    if message:
        raise ParjamError(message)


def print_summary(res, out):
    from parjam import units

    k = units.text("stiffness")  # trial energies <dR|M|dR> and omega^2 of unit modes
    s = res.summary()
    cs = res.cs
    exp = f"{s['expected']}" if s["expected"] is not None else "n/a (not isostatic)"
    mismatch = s["expected"] is not None and s["count"] != s["expected"]
    lines = [
        f"planes            {' '.join(p.label for p in cs.planes)}",
        f"N' / Nc / excess  {s['N_active']} / {s['Nc']} / {s['excess']:+d}",
        f"cut contacts q    {s['q']}",
        f"null space        {s['count']} (d + q - 1 = {exp}{'  MISMATCH' if mismatch else ''})",
        f"  trivial         {s['trivial']} translations (not in the basis)",
        f"  localised       {s['localised']} (particles left with < d contacts)",
        f"  basis           {s['n_soft']} modes, gap {s['gap']:.3e} k, Eq. 3 residual "
        f"{s['eq3_residual']:.1e}, |V^T V - I| {s['orthonormality']:.1e}",
        f"f(x) minimum c    {s['c']:.3f} ({s['c_nontrivial']:.3f} without the localised modes)",
        "q'/q              " + "  ".join(f"e0={e0:g}: {fr:.3f}" for e0, fr in res.fractions),
        f"trial modes       q' = {s['q_prime']} with e > {s['e0']:g}: max energy "
        f"{_fmt(s['trial_energy_max'])} <= omega_L^2 = {s['omega_L2']:.3e} {k} (Eq. kkk)",
        f"variational       {s['n_below_2omega_t2']} eigenmodes with omega^2 <= 2 omega_t^2 = "
        f"{2 * s['omega_t2']:.3e} {k} (need >= q'/2 = {s['q_prime'] / 2:g}): "
        f"{'ok' if s['variational_ok'] else 'VIOLATED'}",
        f"time / memory     count {res.solver['seconds_count']:.2f} s, null space "
        f"{res.solver['seconds_null_space']:.2f} s, analysis "
        f"{res.solver['seconds_analysis']:.2f} s; peak {res.solver['peak_rss_mb']:.0f} MB per rank",
        f"written           {out}",
    ]
    print("\n".join(lines), flush=True)


def _fmt(x):
    return "n/a" if x is None else f"{x:.3e}"
