"""Scenes: a study described once in a TOML file, parsed and validated.

A scene names the systems (d, N, dispersity, ratio, alpha), the protocol (a dphi ladder or target
pressures), the ensemble (members, seed) and the observables wanted.  :func:`load` parses it with
the standard library's tomllib into a :class:`Scene`; every unknown key, wrong type or impossible
combination is a one-line :class:`ParjamError` naming the key, raised before any work starts.
parjam.study.plan derives the stages from it.

The format is documented in README.md ("Scenes") and by the bundled scenes in ``scenes/``.
"""

import os
import tomllib
from dataclasses import dataclass, field

from parjam import softmodes
from parjam.files import inputs
from parjam.study.tables import Table, show
from parjam.vib import solver_choice
from parjam.errors import ParjamError
from parjam.pack.protocol import (DEFAULT_ALPHA, DEFAULT_DISPERSITY, DEFAULT_ENERGY_WINDOW,
                                  DEFAULT_FTOL, DEFAULT_RATIO, DISPERSITIES, LADDERS,
                                  PHIC_METHODS, PackingProtocol, check_tolerances)
from parjam.vib.solver_choice import MATRICES


# --------------------------------------------------------------------------- the parsed scene

@dataclass
class System:
    d: int
    n: int
    dispersity: str
    ratio: float
    alpha: float
    name: str  # one path component (parjam.files.inputs.component): it names stages and files
    title: str = None  # the name as the scene gives it, when the file names had to change it

    @property
    def max_dof(self):
        return self.d * self.n

    def key(self):
        return {"d": self.d, "n": self.n, "dispersity": self.dispersity,
                "ratio": self.ratio, "alpha": self.alpha}


@dataclass
class Protocol:
    dphi: list = None
    pressure: list = None
    ladder: str = "compress"
    ftol: float = DEFAULT_FTOL
    energy_window: tuple = DEFAULT_ENERGY_WINDOW
    phi_start: float = None
    phic_method: str = "bisect"  # or "extrapolate": no phi_c state is written (parjam.pack.ensemble)

    @property
    def has_phi_c(self):
        return self.phic_method == "bisect"

    @property
    def values(self):
        return self.dphi if self.dphi is not None else self.pressure

    def labels(self):
        """State labels in the packing files' naming (parjam.pack.packing): phi_c first (when the
        bisection writes it)."""
        fmt = "dphi{:.1e}" if self.dphi is not None else "p{:.1e}"
        return ["phi_c"] * self.has_phi_c + [fmt.format(v) for v in sorted(self.values)]

    def label_of(self, value):
        if value == "phi_c":
            return "phi_c"
        return ("dphi{:.1e}" if self.dphi is not None else "p{:.1e}").format(value)

    def key(self):
        key = {"dphi": self.dphi, "pressure": self.pressure, "ladder": self.ladder,
               "ftol": self.ftol, "energy_window": list(self.energy_window),
               "phi_start": self.phi_start}
        if self.phic_method != "bisect":  # the bisection's stage keys stay as they were
            key["phic_method"] = self.phic_method
        return key


@dataclass
class Scene:
    name: str
    path: str
    systems: list
    protocol: Protocol
    members: int
    seed: int
    observables: dict  # name -> dict of validated options
    solver: dict = field(default_factory=dict)
    title: str = None  # the name as the scene gives it, when the directory name had to change it

    def packing_protocol(self, system, out):
        """The packing protocol (parjam.pack.protocol) of one system's pack stage, written to
        ``out``: what ``parjam pack`` with the same settings would make."""
        p = self.protocol
        return PackingProtocol(
            dim=system.d, n=system.n, out=out, alpha=system.alpha, dispersity=system.dispersity,
            ratio=system.ratio, seed=self.seed, members=self.members, dphi=p.dphi,
            pressure=p.pressure, ladder=p.ladder, phic_method=p.phic_method,
            phi_start=p.phi_start, ftol=p.ftol, energy_window=p.energy_window)


# --------------------------------------------------------------------------- parsing

TOP_KEYS = ("scene", "system", "protocol", "ensemble", "observables", "solver")
OBSERVABLES = ("contacts", "dos", "lowest", "omega_star", "trans", "softmodes", "moduli",
               "fluctuations", "pictures")


MAX_SCENE_BYTES = 1 << 20  # a scene is a page of text; a larger file is not one
MAX_DEPTH = 8  # tables and arrays of a scene nest 3 deep ([observables.dos] matrices = [...])


def load(path):
    """Parse and validate the scene file at ``path`` (read through the input policy: a FIFO, a
    directory or a device is refused before it is opened)."""
    path = os.fspath(path)
    if inputs.kind(path) == "missing":
        raise ParjamError(f"{inputs.shown(path)}: no such scene file")
    try:
        data = inputs.read_bytes(path, limit=MAX_SCENE_BYTES)
    except OSError as exc:  # no permission, an I/O error, ...
        raise ParjamError(f"{inputs.shown(path)}: cannot read the scene file "
                          f"({exc.strerror})") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ParjamError(f"{inputs.shown(path)}: not valid TOML ({exc})") from None
    return loads(text, path)


def loads(text, path="<scene>"):
    shown = inputs.shown(path)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ParjamError(f"{shown}: not valid TOML ({exc})") from None
    except RecursionError:  # tomllib recurses once per nested array or inline table
        raise ParjamError(f"{shown}: arrays or tables nested too deeply (a scene nests "
                          f"{MAX_DEPTH} deep at most)") from None
    deep = _depth(data)
    if deep > MAX_DEPTH:
        raise ParjamError(f"{shown}: arrays or tables nested {deep} deep (a scene nests "
                          f"{MAX_DEPTH} deep at most)")
    return parse(data, shown)


def _depth(value):
    """How deeply lists and tables nest in ``value`` (iteratively: no recursion limit)."""
    deepest, stack = 0, [(value, 0)]
    while stack:
        item, level = stack.pop()
        if isinstance(item, dict):
            children = item.values()
        elif isinstance(item, list):
            children = item
        else:
            continue
        deepest = max(deepest, level + 1)
        if level + 1 <= MAX_DEPTH:  # deeper: already refused, no need to walk further
            stack.extend((child, level + 1) for child in children)
    return deepest


def parse(data, path="<scene>"):
    top = Table(data, "top level", path)
    meta = Table(top.raw("scene", {}), "scene", path)
    title = meta.str("name", os.path.splitext(os.path.basename(path))[0] or "scene")
    name = _component(title, path, "[scene] name")
    meta.str("description", "")
    meta.done()
    systems = _systems(top.raw("system"), path)
    protocol = _protocol(top.raw("protocol"), path)
    for s in systems:  # the same refusals as parjam pack's --ftol/--energy-window
        try:
            check_tolerances(protocol.ftol, protocol.energy_window, s.alpha, s.d,
                             names=("protocol.ftol", "protocol.energy_window"))
        except ParjamError as exc:
            raise ParjamError(f"{path}: {exc}") from None
    ens = Table(top.raw("ensemble", {}), "ensemble", path)
    members = ens.int("members", 1, lo=1, hi=100_000)
    seed = ens.int("seed", 0, lo=0)
    ens.done()
    solver = _solver(top.raw("solver", {}), path)
    obs = _observables(top.raw("observables"), path, systems, protocol)
    top.done()
    return Scene(name, path, systems, protocol, members, seed, obs, solver,
                 title if title != name else None)


def _component(text, path, what):
    """A name from the scene as one path component (parjam.files.inputs.component): ``../X``,
    ``/abs`` or ``a/b`` stay inside the results directory."""
    try:
        return inputs.component(text, what)
    except ParjamError as exc:
        raise ParjamError(f"{path}: {exc}") from None


def _systems(raw, path):
    if raw is None:
        raise ParjamError(f"{path}: no [[system]] table: give at least d and N")
    tables = raw if isinstance(raw, list) else [raw]
    out = []
    for k, data in enumerate(tables):
        t = Table(data, f"system {k + 1}", path)
        d = t.int("d", None, lo=2, hi=3)
        if d is None:
            t.fail("d", "missing (2 or 3)")
        ns = t.list("N")
        if ns is None:
            t.fail("N", "missing (number of particles, or a list of them)")
        for n in ns:
            if isinstance(n, bool) or not isinstance(n, int) or not 16 <= n <= 50_000_000:
                t.fail("N", f"must be integers in [16, 5e7], got {show(n)}")
        disp = t.str("dispersity", DEFAULT_DISPERSITY[d], DISPERSITIES)
        ratio = t.float("ratio", DEFAULT_RATIO, lo=1.0, hi=10.0)
        alpha = t.float("alpha", DEFAULT_ALPHA, lo=1.0, lo_open=True, hi=10.0)
        name = t.str("name", None)
        t.done()
        for n in ns:
            label = name or f"d{d}-{disp}-N{n}" + ("" if alpha == 2.0 else f"-alpha{alpha:g}")
            if name and len(ns) > 1:
                label = f"{name}-N{n}"
            safe = _component(label, path, f"[system {k + 1}] name")
            out.append(System(d, n, disp, ratio, alpha, safe, label if label != safe else None))
    names = [s.title or s.name for s in out]
    if len(set(names)) != len(names):
        raise ParjamError(f"{path}: [system] two systems share the name "
                          f"{show(next(x for x in names if names.count(x) > 1))}")
    try:  # two names that give one directory name (also up to case) would share their files
        inputs.distinct({s.title or s.name: s.name for s in out}, "[system] names")
    except ParjamError as exc:
        raise ParjamError(f"{path}: {exc}") from None
    return out


def _protocol(raw, path):
    if raw is None:
        raise ParjamError(f"{path}: no [protocol] table: give dphi = [...] or pressure = [...]")
    t = Table(raw, "protocol", path)
    dphi = t.numbers("dphi", None, lo=0.0, hi=1.0, lo_open=True)
    pressure = t.numbers("pressure", None, lo=0.0, hi=10.0, lo_open=True)
    if (dphi is None) == (pressure is None):
        t.fail("dphi", "give exactly one of dphi = [...] (a ladder) or pressure = [...]")
    ladder = t.str("ladder", "compress", LADDERS)
    if pressure is not None and t.has("ladder"):
        t.fail("ladder", "applies to a dphi ladder, not to target pressures")
    ftol = t.float("ftol", DEFAULT_FTOL, lo=0.0, hi=1e-3, lo_open=True)
    window = t.numbers("energy_window", list(DEFAULT_ENERGY_WINDOW), lo=0.0, lo_open=True)
    if len(window) != 2 or not window[0] < window[1]:
        t.fail("energy_window", f"must be [LOW, HIGH] with 0 < LOW < HIGH, got {window}")
    phi_start = t.float("phi_start", None, lo=0.05, hi=1.5)
    phic_method = t.str("phic_method", "bisect", PHIC_METHODS)
    t.done()
    vals = dphi if dphi is not None else pressure
    if len({f"{v:.1e}" for v in vals}) != len(vals):
        t.fail("dphi" if dphi is not None else "pressure",
               "two values coincide to 2 significant digits (state labels would collide)")
    return Protocol(sorted(dphi) if dphi else None, sorted(pressure) if pressure else None,
                    ladder, ftol, tuple(window), phi_start, phic_method)


def _solver(raw, path):
    t = Table(raw, "solver", path)
    out = {"tol": t.float("tol", 1e-10, lo=solver_choice.TOL_MIN, hi=solver_choice.TOL_MAX),
           "dense_max_dof": t.int("dense_max_dof", solver_choice.WHOLE_MAX_DOF, lo=1,
                                  hi=40_000),
           "small_dof": t.int("small_dof", solver_choice.PARTIAL_DENSE_MAX_DOF, lo=0)}
    t.done()
    return out


def _states(t, protocol, default):
    """Protocol states an observable applies to: "phi_c", or values of the ladder/pressures."""
    raw = t.raw("at", None)
    if raw is None:
        return default
    raw = raw if isinstance(raw, list) else [raw]
    if not raw:
        t.fail("at", "must not be empty")
    labels = set(protocol.labels())
    out = []
    for v in raw:
        if v == "phi_c":
            if not protocol.has_phi_c:
                t.fail("at", "there is no phi_c state with phic_method = \"extrapolate\" (phi_c "
                             "is extrapolated, not reached): use the smallest protocol value")
            out.append("phi_c")
            continue
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            t.fail("at", f"must list \"phi_c\" or protocol values, got {show(v)}")
        label = protocol.label_of(float(v))
        if label not in labels:
            t.fail("at", f"{v:g} is not one of the protocol's values "
                         f"{', '.join(f'{x:g}' for x in protocol.values)}")
        out.append(label)
    return list(dict.fromkeys(out))


def _obs_table(raw, name, path):
    if raw is True:
        raw = {}
    if raw is False:
        return None
    return Table(raw, f"observables.{name}", path)


def _observables(raw, path, systems, protocol):
    if raw is None:
        raise ParjamError(f"{path}: no [observables] table: nothing to compute")
    top = Table(raw, "observables", path)
    ladder = [lab for lab in protocol.labels() if lab != "phi_c"]
    lowest_state = [ladder[0]]  # closest to jamming
    min_modes = min(s.d * s.n - s.d for s in systems)
    out = {}
    for name in OBSERVABLES:
        if not top.has(name):
            continue
        t = _obs_table(top.raw(name), name, path)
        if t is None:
            continue
        out[name] = globals()[f"_obs_{name}"](t, protocol, ladder, lowest_state, min_modes)
        t.done()
    top.done()
    if not out:
        raise ParjamError(f"{path}: [observables] is empty: nothing to compute")
    return out


def _window(t, key="window"):
    w = t.numbers(key, None)
    if w is None:
        return None
    if len(w) != 2 or not w[0] < w[1]:
        t.fail(key, f"must be [OMEGA_A, OMEGA_B] with OMEGA_A < OMEGA_B, got {w}")
    if w[0] < 0:
        t.fail(key, f"slicing window below zero ({w[0]:g}): frequencies start at 0")
    return tuple(w)


def _k(t, min_modes, default=None):
    k = t.int("k", default, lo=1)
    if k is not None and k > min_modes:
        t.fail("k", f"{k} exceeds the {min_modes} non-translational modes (d N - d) of the "
                    f"smallest system")
    return k


def _obs_contacts(t, protocol, ladder, lowest, min_modes):
    return {"at": _states(t, protocol, protocol.labels())}


def _obs_dos(t, protocol, ladder, lowest, min_modes):
    out = {"matrices": t.strings("matrices", ["full"], MATRICES),
           "bins": t.int("bins", 40, lo=1, hi=100_000), "log_bins": t.bool("log_bins"),
           "omega_min": t.float("omega_min", None, lo=0.0, lo_open=True),
           "window": _window(t), "at": _states(t, protocol, ladder)}
    if out["log_bins"] and out["window"] is not None and out["window"][0] == 0 \
            and out["omega_min"] is None:
        t.fail("log_bins", "log bins over a window starting at 0 need omega_min > 0")
    method = t.str("method", "dense", ("dense", "kpm"))
    if method == "dense":  # the dense options only: the stage keys stay as they were
        for key in ("moments", "probes", "max_moments"):
            if t.has(key):
                t.fail(key, "applies to method = \"kpm\"")
        return out
    if out["window"] is not None:
        t.fail("window", "KPM gives the whole D(omega): no window with method = \"kpm\"")
    moments = t.raw("moments", "auto")
    if moments != "auto":
        moments = t.int("moments", lo=16, hi=65536)
    out.update(method="kpm", moments=moments, probes=t.int("probes", 8, lo=1, hi=1024),
               max_moments=t.int("max_moments", 4096, lo=16, hi=65536))
    return out


def _obs_lowest(t, protocol, ladder, lowest, min_modes):
    k = _k(t, min_modes)
    if k is None:
        t.fail("k", "missing: the number of lowest modes")
    return {"k": k, "matrices": t.strings("matrices", ["full"], MATRICES),
            "vectors": t.bool("vectors"), "at": _states(t, protocol, ladder)}


def _obs_omega_star(t, protocol, ladder, lowest, min_modes):
    window, k = _window(t), _k(t, min_modes)
    if window is not None and k is not None:
        t.fail("k", "give a window or k, not both")
    plateau = t.str("plateau", "spectrum", ("spectrum", "kpm"))
    if plateau == "kpm" and window is None and k is None:
        t.fail("plateau", "\"kpm\" is for partial spectra (k or window): a whole spectrum has "
                          "its own plateau")
    return {"matrices": t.strings("matrices", ["relaxed"], MATRICES), "window": window, "k": k,
            "plateau": plateau, "at": _states(t, protocol, ladder)}


def _obs_trans(t, protocol, ladder, lowest, min_modes):
    return {"matrix": t.str("matrix", "full", MATRICES), "k": _k(t, min_modes),
            "at": _states(t, protocol, lowest)}


def _obs_softmodes(t, protocol, ladder, lowest, min_modes):
    cuts = t.strings("cuts", None)
    sub = t.int("subdivide", None, lo=1, hi=1000)
    if cuts is None and sub is None:
        cuts = ["x=0.5"]
    for c in cuts or []:
        try:
            softmodes.parse_cut(c, 3)
        except ParjamError as exc:
            t.fail("cuts", str(exc).replace("--cut ", ""))
    return {"cuts": cuts or [], "subdivide": sub,
            "e0": t.float("e0", 0.1, lo=0.0, hi=1.0, lo_open=True),
            "bins": t.int("bins", 10, lo=2, hi=100_000),
            "allow_hyperstatic": t.bool("allow_hyperstatic"),
            "at": _states(t, protocol, ["phi_c"] if protocol.has_phi_c else lowest)}


def _obs_moduli(t, protocol, ladder, lowest, min_modes):
    return {"at": _states(t, protocol, ladder)}


def _obs_fluctuations(t, protocol, ladder, lowest, min_modes):
    m = t.int("max_divisions", 8, lo=1, hi=1000)
    return {"max_divisions": m,
            "at": _states(t, protocol, ["phi_c"] * protocol.has_phi_c + lowest)}


def _obs_pictures(t, protocol, ladder, lowest, min_modes):
    return {"dpi": t.int("dpi", 150, lo=20, hi=600)}
