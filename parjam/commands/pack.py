"""``parjam pack``: an ensemble of jammed packings (phi_c bisection, dphi ladder, pressures)."""

import contextlib
import glob
import os
import sys

import numpy as np

from parjam.errors import ParjamError, UnjammedError
from parjam.progress import member
from parjam.pack.protocol import (DEFAULT_ALPHA, DEFAULT_DPHI, DEFAULT_ENERGY_WINDOW, DEFAULT_FTOL,
                                  DEFAULT_PHI_START, DISPERSITIES, DEFAULT_RATIO, LADDERS, PHIC_METHODS,
                             PackingProtocol, check_tolerances)
from parjam.ranks import GroupFailures, member_groups

MAX_MEMBERS = 1_000_000
DEFAULT_DIM, DEFAULT_N, DEFAULT_DISPERSITY = 3, 256, "mono"
#: what a --from file decides (its d, N, diameters and phi): refused when given with it
FILE_DECIDES = (("dim", "--dim"), ("n", "--n"), ("dispersity", "--dispersity"),
                ("ratio", "--ratio"), ("phi_start", "--phi-start"))


def add_parser(sub):
    p = sub.add_parser(
        "pack", help="generate jammed packings",
        description="Random (infinite-temperature) start, minimisation to force balance, phi_c by "
        "the O'Hern bisection, then phi_c + dphi for each dphi (or target pressures). One HDF5 "
        "file per member and state in --out. Members are spread over MPI ranks; with fewer "
        "members than ranks, ranks share a member (distributed minimisation).")
    # d, N, dispersity and ratio default to None so that --from can tell them given: the file
    # decides them, and a value given with it would be ignored
    p.add_argument("--dim", type=int, help="dimension d, 2 or 3 (default 3)")
    p.add_argument("--n", type=int, help=f"number of particles (>= 16; default {DEFAULT_N})")
    p.add_argument("--dispersity", help="mono | bi (50:50) | poly (uniform) (default mono)")
    p.add_argument("--ratio", type=float,
                   help="large/small diameter ratio for bi, width (max/min) for poly "
                   f"({DEFAULT_RATIO})")
    p.add_argument("--alpha", type=float, default=DEFAULT_ALPHA,
                   help="potential exponent (2 harmonic, 2.5 Hertz); must be > 1")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--dphi", type=float, nargs="+", help="ladder of phi - phi_c (default "
                   "1e-6 1e-4 1e-2)")
    g.add_argument("--pressure", type=float, nargs="+", help="target pressures instead")
    g.add_argument("--phi", type=float, help="quench at this fixed phi only (no phi_c search)")
    p.add_argument("--phic-method", choices=PHIC_METHODS, default="bisect",
                   help="bisect: O'Hern bisection to E/N in --energy-window (exact, slow for "
                   "large N); extrapolate: decompress from a jammed start at --phi-start, "
                   "phi_c = phi - alpha E phi/(p V) from the state nearest the smallest dphi "
                   "(no phi_c file; agrees with the bisection of the same configuration to "
                   "1-2%% of dphi at 1e-3, < 0.6%% at 1e-5; for large N)")
    p.add_argument("--ladder", choices=LADDERS, default="compress",
                   help="compress up from phi_c, or decompress from the largest dphi downwards")
    p.add_argument("--phi-start", type=float, help="phi of the random start (0.86 in 2D, "
                   "0.66 in 3D)")
    p.add_argument("--from", dest="start", metavar="FILE",
                   help="start from this packing (e.g. made by `parjam import`) instead of "
                   "random positions: one member, its d, N and diameters; --alpha applies")
    p.add_argument("--seed", type=int, default=0, help="ensemble seed (member m uses [seed, m])")
    p.add_argument("--members", type=int, default=1, help="ensemble size")
    p.add_argument("--ftol", type=float, default=DEFAULT_FTOL, help="max |F| tolerance (1e-13); "
                   "returned states are balanced further, to 1e-5 of their mean contact force "
                   "(down to the forces' round-off); values above the contact forces of the "
                   "energy window or below the round-off are refused")
    p.add_argument("--energy-window", type=float, nargs=2, default=DEFAULT_ENERGY_WINDOW,
                   metavar=("LOW", "HIGH"), help="E/N window of the bisection (1e-16 2e-16); "
                   "phi_c is then refined from the jammed side (virial relation) and its "
                   "resolution recorded; windows whose overlaps are at round-off or far from "
                   "jamming are refused")
    p.add_argument("--no-phic-file", action="store_true", help="do not write the phi_c state")
    p.add_argument("--out", default="packings", help="output directory (default ./packings)")
    p.add_argument("--no-resume", dest="resume", action="store_false",
                   help="recompute every member; by default the members that DIR/manifest.json "
                   "lists as finished (files present, sha256 intact) are skipped, and a DIR "
                   "holding results of other parameters is refused")
    p.add_argument("--checkpoint-every", type=float, default=300.0, metavar="SECONDS",
                   help="write DIR/.checkpoint/memberM.h5 at most this often (default 300; 0: "
                   "never): a killed or requeued run then resumes inside the member, not from "
                   "its random start")
    p.add_argument("--force", action="store_true",
                   help="run even if the memory/time estimate does not fit this machine")
    p.add_argument("--dry-run", action="store_true",
                   help="print the memory/time estimate and whether it fits this machine; stop")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    p.set_defaults(run=run, reads=lambda a: [("--from", a.start)])


def validate(args):
    if getattr(args, "start", None):
        given = [option for attr, option in FILE_DECIDES if getattr(args, attr, None) is not None]
        if given:
            raise ParjamError(f"--from {args.start} decides d, N, the diameters and phi: "
                              f"{', '.join(given)} cannot be given with it")
        start_from_file(args)
    for attr, default in (("dim", DEFAULT_DIM), ("n", DEFAULT_N),
                          ("dispersity", DEFAULT_DISPERSITY), ("ratio", DEFAULT_RATIO)):
        if getattr(args, attr, None) is None:
            setattr(args, attr, default)
    if args.dim not in (2, 3):
        raise ParjamError(f"--dim must be 2 or 3, got {args.dim}")
    if args.n < 16:
        raise ParjamError(f"--n must be at least 16, got {args.n}")
    if args.n > 50_000_000:
        raise ParjamError(f"--n {args.n} is absurdly large")
    if args.dispersity not in DISPERSITIES:
        raise ParjamError(f"unknown dispersity {args.dispersity!r}; choose from "
                          f"{', '.join(DISPERSITIES)}")
    if not np.isfinite(args.alpha) or args.alpha <= 1.0:
        raise ParjamError(f"--alpha must be > 1, got {args.alpha}")
    if not np.isfinite(args.ratio) or args.ratio < 1.0 or args.ratio > 10.0:
        raise ParjamError(f"--ratio must lie in [1, 10], got {args.ratio}")
    if not 1 <= args.members <= MAX_MEMBERS:
        raise ParjamError(f"--members must lie in [1, {MAX_MEMBERS}], got {args.members}")
    if not 0 <= args.seed < 2**63:
        raise ParjamError(f"--seed must be a non-negative integer below 2^63, got {args.seed}")
    if not (0 < args.ftol < 1e-3):
        raise ParjamError(f"--ftol must lie in (0, 1e-3), got {args.ftol}")
    if not (np.isfinite(args.checkpoint_every) and args.checkpoint_every >= 0):
        raise ParjamError(f"--checkpoint-every must be >= 0 seconds, got {args.checkpoint_every}")
    lo, hi = args.energy_window
    if not (0 < lo < hi):
        raise ParjamError(f"--energy-window needs 0 < LOW < HIGH, got {lo} {hi}")
    # the energy window defines phi_c only where the bisection runs (not for a --phi quench)
    check_tolerances(args.ftol, args.energy_window, args.alpha, args.dim,
                     bisection=args.phi is None)
    for phi in [args.phi, args.phi_start]:
        if phi is not None and not (0.05 <= phi < 1.0 + 0.5 * (args.dim == 2)):
            raise ParjamError(f"volume fraction {phi} is out of range (0.05 .. 1)")
    for dphi in args.dphi or []:
        if not (0.0 < dphi <= 1.0):
            raise ParjamError(f"--dphi values must lie in (0, 1], got {dphi}")
    for p in args.pressure or []:
        if not (0.0 < p < 10.0) or not np.isfinite(p):
            raise ParjamError(f"--pressure values must lie in (0, 10), got {p}")
    if args.phi is None and args.pressure is None and args.dphi is None:
        args.dphi = list(DEFAULT_DPHI)
    state_labels(args)  # two values that give one file name: refused here, before any work
    if args.phic_method == "extrapolate" and args.phi is not None:
        raise ParjamError("--phic-method extrapolate needs --dphi or --pressure, not --phi")
    if args.phi_start is None:
        args.phi_start = DEFAULT_PHI_START[args.dim]


def state_labels(args):
    """The labels of the states a member writes (its files are memberM_LABEL.h5, labelled as
    parjam.pack.packing names them: dphi and pressures to 2 significant digits); two values
    with one label would write one file and lose the other, so they are refused."""
    if args.phi is not None:
        return [f"phi{args.phi:.4f}"]
    option, fmt = ("--dphi", "dphi{:.1e}") if args.dphi else ("--pressure", "p{:.1e}")
    labels = {}
    for value in args.dphi or args.pressure:
        label = fmt.format(value)
        if label in labels:
            raise ParjamError(f"{option} {labels[label]:g} and {value:g} give the same state "
                              f"label {label} (2 significant digits): their files would "
                              f"overwrite each other; make them differ")
        labels[label] = value
    return ["phi_c"] * (args.phic_method == "bisect") + list(labels)


def fits_machine(args, world):
    """The memory/time estimate of this ensemble against the machine (parjam.resources),
    before any work; refused unless --force.  True for --dry-run (printed, nothing to do)."""
    from parjam import resources

    states = len(args.dphi or args.pressure or [args.phi]) + (args.phi is None)
    rounds = -(-args.members // min(args.members, world.getSize()))  # members per group
    seconds = rounds * resources.pack_seconds(args.dim, args.n, states, args.phic_method)
    memory = resources.pack_memory_mb(args.n, args.dim)
    if getattr(args, "dry_run", False):
        text = resources.describe(memory, seconds, resources.ranks_on_node(world.tompi4py()))
        if world.getRank() == 0:
            print(f"pack of {args.members} member(s) at N = {args.n}, {states} state(s): "
                  f"~{memory:.0f} MB per rank, ~{seconds:.0f} s on {world.getSize()} rank(s)\n"
                  f"{text}", flush=True)
        return True
    resources.check(world, memory, seconds, args.force,
                    f"pack of {args.members} member(s) at N = {args.n}")
    return False


def start_from_file(args):
    """--from FILE: d, N, phi_start and the dispersity label come from the file, read by rows
    on every rank of the world (parjam.pack.filestart.describe: no rank reads all N particles); each
    member's group reads its own rows again when it starts (filestart.start_rows)."""
    from parjam import env
    from parjam.files import rowio
    from parjam.files.h5md import sha256
    from parjam.pack.filestart import describe

    if args.members != 1:
        raise ParjamError(f"--from starts one configuration: --members must be 1, got "
                          f"{args.members}")
    world = env.petsc().COMM_WORLD
    about = describe(world, rowio.read_rows(world, args.start))
    args.dim, args.n, args.phi_start = about.d, about.n, about.phi
    args.dispersity, args.ratio = about.dispersity, about.ratio
    args.start_sha256 = sha256(args.start)


def prepare_output(args, params):
    """World rank 0: make DIR, refuse other parameters, find the finished members, write the
    manifest.  Returns ({member: files} finished, [notes])."""
    from parjam.files import manifest

    try:
        os.makedirs(args.out, exist_ok=True)
    except OSError as exc:
        raise ParjamError(f"cannot create output directory {args.out}: {exc}") from None
    if not os.access(args.out, os.W_OK):
        raise ParjamError(f"cannot write to output directory {args.out}")
    manifest.check_parameters(args.out, params)
    notes = [f"removed stale temporary file {name}"
             for name in manifest.remove_stale_temporaries(args.out)]
    done, damaged = manifest.finished_members(args.out, params)
    notes += [f"{member(m)} (member{m:04d}_*): files missing or changed since they were "
              f"written: recomputing"
              for m in damaged]
    if not args.resume:
        done = {}
    manifest.write_manifest(args.out, params, done)
    return done, notes


def _terminate_handler(out):
    """SIGTERM (batch systems send it before SIGKILL): remove this process's temporary files,
    say so, and end every rank at once.  Raising an exception instead would surface wherever the
    signal lands (even inside a ctypes call, as a different exception)."""

    def handler(signum, frame):
        from mpi4py import MPI

        from parjam.files import manifest

        for directory in manifest.temporary_dirs(out):
            for path in glob.glob(os.path.join(directory, f".*.tmp{os.getpid()}")):
                with contextlib.suppress(OSError):
                    os.remove(path)
        print("parjam: interrupted (SIGTERM): finished members are kept, and members in progress "
              "have their checkpoints; the same command resumes the run", file=sys.stderr,
              flush=True)
        if MPI.COMM_WORLD.Get_size() > 1:
            MPI.COMM_WORLD.Abort(128 + signum)
        os._exit(128 + signum)

    return handler


def run(args):
    import signal
    import threading

    if threading.current_thread() is threading.main_thread():
        old = signal.signal(signal.SIGTERM, _terminate_handler(args.out))
        try:
            return _run(args)
        finally:
            signal.signal(signal.SIGTERM, old)
    return _run(args)


def _run(args):
    validate(args)
    from parjam import env
    from parjam.files import manifest, outputs
    from parjam.pack import stability
    from parjam.study.members import (MemberIncomplete, pack_member, print_table,
                                      rows_from_files, stopped_line)
    from parjam.progress import Progress, Relay

    PETSc = env.petsc()
    world = PETSc.COMM_WORLD
    mpi = world.tompi4py()
    protocol = PackingProtocol.from_namespace(args)
    params = manifest.run_parameters(protocol)
    stability.Settings.from_options()  # bad -stability_* options: refused before any work
    if fits_machine(args, world):  # --dry-run: the estimate only
        return 0
    # the directory, and what pack writes in it: no symlink, FIFO or device at a member's,
    # the manifest's or a checkpoint's name, none of them the --from file (by identity)
    outputs.check(world, dirs=[("--out", args.out)], inputs=[args.start] if args.start else [],
                  trees=[("--out", args.out, manifest.owned)])
    outcome = None
    if world.getRank() == 0:
        try:
            outcome = prepare_output(args, params)
        except ParjamError as exc:
            outcome = str(exc)
    outcome = mpi.bcast(outcome, root=0)
    if isinstance(outcome, str):
        raise ParjamError(outcome)
    done, notes = outcome
    done = {m: files for m, files in done.items() if m < args.members}
    relay = Relay(mpi)  # every group's progress lines reach world rank 0
    progress = Progress(world, args.quiet, relay=relay)
    for note in notes:
        progress(note)
    if done:
        progress(f"resuming: {len(done)} of {args.members} members already finished in "
                 f"{args.out} (skipped)")
    todo = [m for m in range(args.members) if m not in done]
    comm, mine = member_groups(world, args.members, todo)
    rows, incomplete = [], []
    stage = PETSc.Log.Stage("parjam pack")
    stage.push()
    # a group's one-line failure (a full disk at a member's file or checkpoint) ends every
    # group, with that line, instead of leaving the others waiting for it (parjam.ranks)
    failures = GroupFailures(mpi)
    failure = None
    try:
        for m in mine:
            if comm.tompi4py().bcast(failures.pending() if comm.getRank() == 0 else None):
                break  # another group failed: its line ends the run
            try:
                rows += pack_member(protocol, m, comm,
                                    progress.group(comm, f"{member(m, args.members)}: "),
                                    params)
            except MemberIncomplete as exc:  # its jammed states are written; the others go on
                rows += exc.rows
                if comm.getRank() == 0:
                    incomplete.append((exc.member, exc.step, exc.n_states))
            except ParjamError as exc:
                if not exc.collective:  # one rank alone: the command line aborts every rank
                    raise
                failure = (exc.exit_code, str(exc))
                failures.announce(*failure)
                break
    finally:
        stage.pop()
    relay.close()
    failure = failures.agree(failure)
    if failure is not None:
        error = ParjamError(failure[1])
        error.exit_code = failure[0]
        raise error
    all_rows = mpi.gather(rows, root=0)
    incomplete = mpi.gather(incomplete, root=0)
    incomplete = [entry for part in (incomplete or []) for entry in part]

    def finish():  # rank 0; a full disk at the manifest is one line on every rank
        from parjam.files import checkpoint

        checkpoint.remove_empty_directory(args.out)
        finished, _ = manifest.finished_members(args.out, params)
        manifest.write_manifest(args.out, params, finished,
                                {m: step for m, step, _ in incomplete})

    outputs.on_root(world, finish)
    if world.getRank() == 0:
        for m, files in sorted(done.items()):
            all_rows.append(rows_from_files(args.out, m, files))
        print_table([r for part in all_rows for r in part], args.dim)
        line = stopped_line(incomplete, args.members)
        if line:  # after the table, on the same stream: never inside it
            print(line, flush=True)
        sys.stdout.flush()
    # exit 3 (unjammed) when any member's ladder stopped early, though its jammed states are
    # written: the run did not deliver every state it was asked for (docs/explanation/reliability.md)
    return UnjammedError.exit_code if mpi.bcast(bool(incomplete), root=0) else 0
