"""``parjam plot``: PNG figures (matplotlib) from parjam's result files.

    parjam plot RESULTS_DIR --img DIR [--figures fig1,sans,...] [--json FITS.json]
    parjam plot SPECTRUM.h5 [MORE.h5 ...] --out spectra.png

A results directory (or summary files of ``parjam run``) gives the paper's figures and their
fitted laws (parjam.plot.paper, docs/results/reproduction.md); a single result file of another command
gives that command's figure (parjam.plot.spectra, .softmodes, .moduli).  The kind of every input
is recognised from its content.  Drawn on rank 0 only; every PNG is written under a temporary
name and renamed when complete.
"""

import json
import os

import numpy as np

from parjam.errors import ParjamError

#: input kind -> (its figures, the first being the default of --out; several inputs allowed,
#: what the files come from)
KINDS = {
    "spectrum": (("spectra",), True, "parjam modes"),
    "dos": (("dos",), False, "parjam dos"),
    "lengths": (("structure",), False, "parjam lengths --what structure"),
    "moduli": (("moduli",), True, "parjam moduli"),
    "softmodes": (("overlap",), False, "parjam softmodes"),
    "packing": (("softfig", "figs"), False, "parjam pack (2D)"),
    "scaling": (("scaling", "lengths"), True, "scripts/moduli_scaling.py (JSON)"),
    "fxn": (("fx_vs_n",), False, "scripts/fx_vs_n.py collect (JSON)"),
}

MAX_NCUT = 100_000  # more contacts than a plane of any packing parjam handles crosses

FIGURE_HELP = {
    "spectra": "D(omega), eps_perp/eps_par and participation per mode (one or more spectra)",
    "dos": "ensemble D(omega) with error bars and omega*",
    "structure": "F_T(k, omega), F_L(k, omega) with the peaks and sound lines",
    "moduli": "B, G, G_min and G/B against the pressure, one point per file",
    "overlap": "f(x) with its bound c and the extension of every soft mode",
    "softfig": "Fig. 'softfig': a soft mode after --ncut contacts along x = L/2 are cut",
    "figs": "Fig. 'figs': which contacts a plane cut and 2^d sub-boxes remove",
    "scaling": "B, G and G/B against dphi with fitted slopes",
    "lengths": "l*, l_L, l_T against dz",
    "fx_vs_n": "f(x) per N for both cut geometries, c and q'/q against N, trial energies "
               "against L",
}


def add_parser(sub):
    from parjam.plot import paper

    paper_list = "; ".join(f"{n}: {f.what}" for n, f in paper.FIGURES.items())
    file_list = "; ".join(
        f"{kind} file ({src}): " + ", ".join(f"{n} ({FIGURE_HELP[n]})" for n in figs)
        for kind, (figs, _, src) in KINDS.items())
    p = sub.add_parser(
        "plot", help="PNG figures from results: the paper's figures and laws, or one file's",
        description="A results directory of parjam run (the bundled scenes' subdirectories "
        f"{', '.join(s for v in paper.SCENES.values() for s in v)}, or the summary files of one "
        "run) or summary-*.h5 files: every figure with data, fits with bootstrap errors over "
        f"members (--json), drawn to --img DIR as repro_NAME.png. Figures: {paper_list}. "
        f"A result file of another command: {file_list}. Drawn on rank 0 only.")
    p.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="a results directory, summary files, or result files of one kind")
    out = p.add_mutually_exclusive_group(required=True)
    out.add_argument("--img", metavar="DIR", help="write every figure to DIR (results: "
                     "repro_NAME.png; otherwise NAME.png)")
    out.add_argument("--out", metavar="PNG", help="write the one figure to this PNG")
    p.add_argument("--figures", metavar="NAME,NAME",
                   help="only these figures (default: every figure the inputs have data for)")
    p.add_argument("--json", metavar="FITS", help="results: write the fitted laws to this JSON")
    p.add_argument("--ncut", type=int, default=20, help="softfig: contacts cut (20)")
    p.add_argument("--omega-max", type=float, help="structure: top of the frequency axis")
    p.add_argument("-q", "--quiet", action="store_true", help="print nothing")
    p.set_defaults(run=run, reads=lambda a: a.inputs, reads_directories=True)


# --------------------------------------------------------------------------- inputs

def classify(path):
    """The kind of one input: "results" (a directory or a summary file of parjam run) or a key
    of KINDS; ParjamError for anything else."""
    import h5py

    from parjam.files import modes_io

    if os.path.isdir(path):
        return "results"
    if not os.path.exists(path):
        raise ParjamError(f"{path}: no such file or directory")
    if not os.path.isfile(path):
        raise ParjamError(f"{path}: not a regular file")
    if path.lower().endswith(".json"):
        try:
            with open(path) as fh:
                data = json.load(fh)
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            raise ParjamError(f"{path}: not a readable JSON file ({exc})") from None
        if isinstance(data, dict) and isinstance(data.get("fits"), dict) and isinstance(
                data.get("rows"), list) and data["rows"]:
            return "scaling"
        if isinstance(data, dict) and data.get("format") == "parjam-fx-vs-n" and isinstance(
                data.get("summary"), dict):
            return "fxn"
        raise ParjamError(f"{path}: not a JSON of scripts/moduli_scaling.py (no fits and rows) "
                          "or of scripts/fx_vs_n.py")
    if not h5py.is_hdf5(path):
        raise ParjamError(f"{path}: not an HDF5 file")
    try:
        with h5py.File(path, "r") as f:
            if "system" in f.attrs and "states" in f.attrs:
                return "results"
            if "modes" in f and f["modes"].attrs.get("format") == modes_io.FORMAT:
                return "spectrum"
            for kind in ("softmodes", "moduli", "lengths"):
                if isinstance(f.get(kind), h5py.Group):
                    return kind
            if isinstance(f.get("dos"), h5py.Group) and "modes" not in f:
                return "dos"
            if "particles" in f:
                return "packing"
    except (OSError, RuntimeError, KeyError) as exc:
        raise ParjamError(f"{path}: unreadable HDF5 file ({exc})") from None
    raise ParjamError(f"{path}: not a result file parjam plot knows (a summary of parjam run, "
                      "a file of parjam modes, dos, lengths, moduli, softmodes or pack)")


def input_kind(paths):
    kinds = {p: classify(p) for p in paths}
    found = set(kinds.values())
    if len(found) > 1:
        raise ParjamError("the inputs mix kinds (" + ", ".join(
            f"{p}: {k}" for p, k in kinds.items()) + "): plot one kind at a time")
    kind = found.pop()
    if kind == "results":
        dirs = [p for p in paths if os.path.isdir(p)]
        if len(dirs) > 1:
            raise ParjamError(f"more than one results directory ({', '.join(dirs)}): give one")
    elif len(paths) > 1 and not KINDS[kind][1]:
        raise ParjamError(f"a {kind} file is plotted alone, got {len(paths)} files")
    return kind


def requested(args, names, where):
    """The figures of --figures (checked against ``names``), or None for all."""
    if args.figures is None:
        return None
    want = [n.strip() for n in args.figures.split(",") if n.strip()]
    if not want:
        raise ParjamError("--figures names no figure")
    bad = [n for n in want if n not in names]
    if bad:
        raise ParjamError(f"unknown figure {', '.join(repr(n) for n in bad)} for {where}: "
                          f"choose from {', '.join(names)}")
    return [n for n in names if n in want]  # drawing order


def check_output(args, inputs):
    """The output policy (parjam.files.outputs) for --out, --img and --json, before any drawing."""
    from parjam.files import outputs

    if args.out is not None and not args.out.lower().endswith(".png"):
        raise ParjamError(f"--out {args.out}: the name must end in .png")
    outputs.check(None, files=[("--out", args.out), ("--json", args.json)],
                  dirs=[("--img", args.img)], inputs=inputs)


def targets(args, names, prefix=""):
    """[(figure, PNG path)]; --out takes exactly one figure."""
    if args.out is not None:
        if len(names) != 1:
            raise ParjamError(f"--out takes one figure, these inputs give {len(names)} "
                              f"({', '.join(names)}): choose one with --figures or use --img")
        return [(names[0], args.out)]
    return [(n, os.path.join(args.img, f"{prefix}{n}.png")) for n in names]


# --------------------------------------------------------------------------- drawing

def run(args):
    from mpi4py import MPI

    if MPI.COMM_WORLD.Get_rank() != 0:
        return 0  # the others wait in the command line's closing reduction (parjam.cli)
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise ParjamError("parjam plot needs matplotlib (pip install matplotlib, or Debian's "
                          "python3-matplotlib)") from None
    check_output(args, args.inputs)
    kind = input_kind(args.inputs)
    if args.json is not None and kind != "results":
        raise ParjamError("--json is for results (fits of the paper's laws); "
                          f"{args.inputs[0]} is a {kind} file")
    try:
        return plot_results(args) if kind == "results" else plot_file(args, kind)
    except ParjamError as exc:  # a failed write (parjam.files.outputs) on this rank, the only one
        raise ParjamError(str(exc)) from None  # drawing: the others learn it at the close


def say(args, text):
    if not args.quiet:
        print(text, flush=True)


def plot_results(args):
    from parjam.plot import paper, pyplot

    dirs = [p for p in args.inputs if os.path.isdir(p)]
    files = [p for p in args.inputs if not os.path.isdir(p)]
    where = dirs[0] if dirs else ", ".join(files)
    names = requested(args, list(paper.FIGURES), "results")
    groups = paper.read_results(dirs[0] if dirs else None, files)
    if not any(groups.values()):
        raise ParjamError(f"{where}: no summary-*.h5 of parjam run (looked in it and in "
                          f"{', '.join(s for v in paper.SCENES.values() for s in v)})")
    have = paper.available(groups, names)
    missing = [n for n in (names or []) if n not in have]
    if missing:
        raise ParjamError(f"no results for figure {', '.join(missing)} in {where} (needs: "
                          + "; ".join(paper.FIGURES[n].what for n in missing) + ")")
    if not have:
        raise ParjamError(f"{where}: the summaries hold the data of no figure")
    plan = targets(args, list(have), "repro_")
    plt = pyplot()
    fits = {}
    for name, path in plan:
        try:
            fig = paper.FIGURES[name].draw(plt, have[name], fits)
        except (KeyError, IndexError, ValueError) as exc:
            plt.close("all")
            raise ParjamError(f"figure {name}: cannot draw from {where} "
                              f"({type(exc).__name__}: {exc})") from None
        say(args, f"wrote {paper.save(plt, fig, path)}")
    if names is None and not args.quiet:
        skipped = [n for n in paper.FIGURES if n not in have]
        if skipped:
            say(args, f"no data for: {', '.join(skipped)}")
    paper.sizes(groups, fits)
    for key, f in fits.items():
        if isinstance(f, dict) and "exponent" in f:
            say(args, f"{key}: exponent {paper.law(f)}, prefactor {f['prefactor']:.4g}")
    if args.json:
        paper.write_json(args.json, fits)
        say(args, f"fits: {args.json}")
    return 0


def plot_file(args, kind):
    from parjam.plot import atomic_png

    figs, _, source = KINDS[kind]
    names = requested(args, list(figs), f"a {kind} file") or (
        [figs[0]] if args.out is not None else list(figs))
    plan = targets(args, names)
    if not 1 <= args.ncut <= MAX_NCUT:
        raise ParjamError(f"--ncut must lie in [1, {MAX_NCUT}] (contacts along one plane of a "
                          f"2D packing), got {args.ncut}")
    if args.omega_max is not None and not (np.isfinite(args.omega_max) and args.omega_max > 0):
        raise ParjamError(f"--omega-max must be positive, got {args.omega_max}")
    data = load(kind, args.inputs)
    for name, path in plan:
        try:
            with atomic_png(path) as tmp:
                DRAW[name](data, tmp, args)
        except (KeyError, IndexError, ValueError, OSError) as exc:
            raise ParjamError(f"figure {name}: cannot draw from {', '.join(args.inputs)} "
                              f"({type(exc).__name__}: {exc})") from None
        say(args, f"wrote {path}")
    return 0


def load(kind, paths):
    """What the figures of ``kind`` take: spectrum dicts, packing, JSON dicts, or the paths."""
    from parjam.files import h5md, modes_io

    if kind == "spectrum":
        return [modes_io.read_spectrum(p) for p in paths]
    if kind == "packing":
        pack = h5md.read_packing(paths[0])
        if pack.d != 2:
            raise ParjamError(f"{paths[0]}: softfig and figs draw 2D packings, this one is "
                              f"{pack.d}D")
        return pack
    if kind == "fxn":
        with open(paths[0]) as fh:
            return json.load(fh)
    if kind == "scaling":
        out = []
        for p in paths:
            with open(p) as fh:
                out.append(json.load(fh))
        return out
    if kind == "lengths":
        import h5py

        with h5py.File(paths[0], "r") as f:
            if "structure" not in f["lengths"]:
                raise ParjamError(f"{paths[0]}: no structure factors (run parjam lengths "
                                  "--what structure)")
    return paths


def _dos(paths, out, args):
    import h5py

    from parjam.plot.spectra import ensemble_dos_figure

    from parjam.plot.labels import describe, title

    about = describe(paths[0])
    with h5py.File(paths[0], "r") as f:
        g = f["dos"]
        err = g["density_error"][()] if "density_error" in g else None
        label, ws = g.attrs.get("matrix", "ensemble"), g.attrs.get("omega_star")
        label = label.decode() if isinstance(label, bytes) else str(label)
        ensemble_dos_figure(g["omega"][()], g["density"][()], err, out, label,
                            None if ws is None else float(ws),
                            title(about.get("n"), about.get("d"), about.get("state"),
                                  about.get("members"), rf"$D(\omega)$ of the {label} matrix"))


def _structure(paths, out, args):
    from parjam.plot.moduli import structure_figure

    structure_figure(paths[0], out, args.omega_max)


def _spectra(specs, out, args):
    from parjam.plot.spectra import spectra_figure

    spectra_figure(specs, out)


def _moduli(paths, out, args):
    from parjam.plot.moduli import moduli_files_figure

    moduli_files_figure(paths, out)


def _overlap(paths, out, args):
    from parjam.plot.softmodes import overlap_figure

    overlap_figure(paths[0], out)


def _softfig(pack, out, args):
    from parjam.plot.softmodes import softfig

    softfig(pack, out, args.ncut)


def _figs(pack, out, args):
    from parjam.plot.softmodes import figs

    figs(pack, out)


def _scaling(results, out, args):
    from parjam.plot.moduli import scaling_figure

    scaling_figure(results, out)


def _fx_vs_n(results, out, args):
    from parjam.plot.softmodes import fx_vs_n_figure

    fx_vs_n_figure(results, out)


def _lengths(results, out, args):
    from parjam.plot.moduli import lengths_figure

    lengths_figure(results, out)


DRAW = {"spectra": _spectra, "dos": _dos, "structure": _structure, "moduli": _moduli,
        "overlap": _overlap, "softfig": _softfig, "figs": _figs, "scaling": _scaling,
        "lengths": _lengths, "fx_vs_n": _fx_vs_n}
