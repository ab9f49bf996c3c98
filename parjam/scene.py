"""Scenes: a study described once in a TOML file, validated and planned.

A scene names the systems (d, N, dispersity, ratio, alpha), the protocol (a dphi ladder or target
pressures), the ensemble (members, seed) and the observables wanted.  :func:`load` parses it with
the standard library's tomllib into a :class:`Scene`; every unknown key, wrong type or impossible
combination is a one-line :class:`ParjamError` naming the key, raised before any work starts.
:func:`plan` derives the stages from the observables and computes only what they need:

- ``pack``: the packings of every member (always);
- ``network``: z, dz, p of every state (always: cheap, and the other stages report them);
- ``spectrum`` per matrix (full / relaxed / stress): only for the states and matrices an
  observable asks for; the solver per state follows from what is needed there:
  the whole spectrum (D(omega), omega* without a window) -> dense LAPACK, eigenvalues only unless
  per-mode sums are wanted; a window -> SLEPc slicing; the k lowest modes -> SLEPc
  shift-and-invert (dense below ``solver.small_dof``).  No relaxed matrix unless asked for, no
  eigenvectors stored unless ``lowest.vectors``;
- ``moduli``, ``softmodes``, ``fluctuations`` only when asked for;
- ``summary``: ensemble means, errors and D(omega) averages of everything computed.

The format is documented in README.md ("Scenes") and by the bundled scenes in ``scenes/``.
"""

import hashlib
import json
import math
import os
import tomllib
from dataclasses import dataclass, field

from parjam.errors import ParjamError

MATRICES = ("full", "relaxed", "stress")
DISPERSITIES = ("mono", "bi", "poly")
DENSE_MAX_DOF = 8000  # whole spectrum by dense LAPACK up to this many degrees of freedom
SMALL_DOF = 600  # the k lowest modes by dense LAPACK below this (cheaper than a factorisation)


# --------------------------------------------------------------------------- the parsed scene

@dataclass
class System:
    d: int
    n: int
    dispersity: str
    ratio: float
    alpha: float
    name: str

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
    ftol: float = 1e-13
    energy_window: tuple = (1e-16, 2e-16)
    phi_start: float = None
    phic_method: str = "bisect"  # or "extrapolate": no phi_c state is written (parjam.ensemble)

    @property
    def has_phi_c(self):
        return self.phic_method == "bisect"

    @property
    def values(self):
        return self.dphi if self.dphi is not None else self.pressure

    def labels(self):
        """State labels in the packing files' naming (parjam.packing): phi_c first (when the
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


# --------------------------------------------------------------------------- validation helpers

class _Table:
    """One TOML table: typed getters that name the key in every error, and a final check that
    no unknown key is left."""

    def __init__(self, data, where, path):
        if not isinstance(data, dict):
            raise ParjamError(f"{path}: [{where}] must be a table, got {type(data).__name__}")
        self.data, self.where, self.path = dict(data), where, path
        self.used = set()

    def fail(self, key, why):
        raise ParjamError(f"{self.path}: [{self.where}] {key}: {why}")

    def has(self, key):
        return key in self.data

    def raw(self, key, default=None):
        self.used.add(key)
        return self.data.get(key, default)

    def int(self, key, default=None, lo=None, hi=None):
        v = self.raw(key, default)
        if v is None:
            return None
        if isinstance(v, bool) or not isinstance(v, int):
            self.fail(key, f"must be an integer, got {v!r}")
        if lo is not None and v < lo or hi is not None and v > hi:
            self.fail(key, f"must lie in [{lo}, {hi if hi is not None else 'inf'}], got {v}")
        return v

    def float(self, key, default=None, lo=None, hi=None, lo_open=False):
        v = self.raw(key, default)
        if v is None:
            return None
        return self.number(key, v, lo, hi, lo_open)

    def number(self, key, v, lo=None, hi=None, lo_open=False):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            self.fail(key, f"must be a finite number, got {v!r}")
        v = float(v)
        if lo is not None and (v < lo or (lo_open and v == lo)):
            self.fail(key, f"must be {'>' if lo_open else '>='} {lo:g}, got {v:g}")
        if hi is not None and v > hi:
            self.fail(key, f"must be <= {hi:g}, got {v:g}")
        return v

    def bool(self, key, default=False):
        v = self.raw(key, default)
        if not isinstance(v, bool):
            self.fail(key, f"must be true or false, got {v!r}")
        return v

    def str(self, key, default=None, choices=None):
        v = self.raw(key, default)
        if v is None:
            return None
        if not isinstance(v, str):
            self.fail(key, f"must be a string, got {v!r}")
        if choices and v not in choices:
            self.fail(key, f"must be one of {', '.join(choices)}, got {v!r}")
        return v

    def list(self, key, default=None, kind=None):
        v = self.raw(key, default)
        if v is None:
            return None
        if not isinstance(v, list):
            v = [v]
        if not v:
            self.fail(key, "must not be empty")
        return v

    def numbers(self, key, default=None, lo=None, hi=None, lo_open=False):
        v = self.list(key, default)
        return None if v is None else [self.number(key, x, lo, hi, lo_open) for x in v]

    def strings(self, key, default=None, choices=None):
        v = self.list(key, default)
        if v is None:
            return None
        for x in v:
            if not isinstance(x, str):
                self.fail(key, f"must be a list of strings, got {x!r}")
            if choices and x not in choices:
                self.fail(key, f"must be among {', '.join(choices)}, got {x!r}")
        if len(set(v)) != len(v):
            self.fail(key, "lists a value twice")
        return v

    def done(self):
        extra = sorted(set(self.data) - self.used)
        if extra:
            raise ParjamError(f"{self.path}: [{self.where}] unknown key {extra[0]!r}"
                              + (f" (and {len(extra) - 1} more)" if len(extra) > 1 else ""))


# --------------------------------------------------------------------------- parsing

TOP_KEYS = ("scene", "system", "protocol", "ensemble", "observables", "solver")
OBSERVABLES = ("contacts", "dos", "lowest", "omega_star", "trans", "softmodes", "moduli",
               "fluctuations", "pictures")


def load(path):
    """Parse and validate the scene file at ``path``."""
    path = os.fspath(path)
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError:
        raise ParjamError(f"{path}: no such scene file") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ParjamError(f"{path}: not valid TOML ({exc})") from None
    except OSError as exc:  # a directory, no permission, ...
        raise ParjamError(f"{path}: cannot read the scene file ({exc.strerror})") from None
    return parse(data, path)


def loads(text, path="<scene>"):
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ParjamError(f"{path}: not valid TOML ({exc})") from None
    return parse(data, path)


def parse(data, path="<scene>"):
    top = _Table(data, "top level", path)
    meta = _Table(top.raw("scene", {}), "scene", path)
    name = meta.str("name", os.path.splitext(os.path.basename(path))[0] or "scene")
    meta.str("description", "")
    meta.done()
    systems = _systems(top.raw("system"), path)
    protocol = _protocol(top.raw("protocol"), path)
    ens = _Table(top.raw("ensemble", {}), "ensemble", path)
    members = ens.int("members", 1, lo=1, hi=100_000)
    seed = ens.int("seed", 0, lo=0)
    ens.done()
    solver = _solver(top.raw("solver", {}), path)
    obs = _observables(top.raw("observables"), path, systems, protocol)
    top.done()
    return Scene(name, path, systems, protocol, members, seed, obs, solver)


def _systems(raw, path):
    if raw is None:
        raise ParjamError(f"{path}: no [[system]] table: give at least d and N")
    tables = raw if isinstance(raw, list) else [raw]
    out = []
    for k, data in enumerate(tables):
        t = _Table(data, f"system {k + 1}", path)
        d = t.int("d", None, lo=2, hi=3)
        if d is None:
            t.fail("d", "missing (2 or 3)")
        ns = t.list("N")
        if ns is None:
            t.fail("N", "missing (number of particles, or a list of them)")
        for n in ns:
            if isinstance(n, bool) or not isinstance(n, int) or not 16 <= n <= 50_000_000:
                t.fail("N", f"must be integers in [16, 5e7], got {n!r}")
        disp = t.str("dispersity", "bi" if d == 2 else "mono", DISPERSITIES)
        ratio = t.float("ratio", 1.4, lo=1.0, hi=10.0)
        alpha = t.float("alpha", 2.0, lo=1.0, lo_open=True, hi=10.0)
        name = t.str("name", None)
        t.done()
        for n in ns:
            label = name or f"d{d}-{disp}-N{n}" + ("" if alpha == 2.0 else f"-alpha{alpha:g}")
            if name and len(ns) > 1:
                label = f"{name}-N{n}"
            out.append(System(d, n, disp, ratio, alpha, label))
    names = [s.name for s in out]
    if len(set(names)) != len(names):
        raise ParjamError(f"{path}: [system] two systems share the name "
                          f"{next(x for x in names if names.count(x) > 1)!r}")
    return out


def _protocol(raw, path):
    if raw is None:
        raise ParjamError(f"{path}: no [protocol] table: give dphi = [...] or pressure = [...]")
    t = _Table(raw, "protocol", path)
    dphi = t.numbers("dphi", None, lo=0.0, hi=1.0, lo_open=True)
    pressure = t.numbers("pressure", None, lo=0.0, hi=10.0, lo_open=True)
    if (dphi is None) == (pressure is None):
        t.fail("dphi", "give exactly one of dphi = [...] (a ladder) or pressure = [...]")
    ladder = t.str("ladder", "compress", ("compress", "decompress"))
    if pressure is not None and t.has("ladder"):
        t.fail("ladder", "applies to a dphi ladder, not to target pressures")
    ftol = t.float("ftol", 1e-13, lo=0.0, hi=1e-3, lo_open=True)
    window = t.numbers("energy_window", [1e-16, 2e-16], lo=0.0, lo_open=True)
    if len(window) != 2 or not window[0] < window[1]:
        t.fail("energy_window", f"must be [LOW, HIGH] with 0 < LOW < HIGH, got {window}")
    phi_start = t.float("phi_start", None, lo=0.05, hi=1.5)
    phic_method = t.str("phic_method", "bisect", ("bisect", "extrapolate"))
    t.done()
    vals = dphi if dphi is not None else pressure
    if len({f"{v:.1e}" for v in vals}) != len(vals):
        t.fail("dphi" if dphi is not None else "pressure",
               "two values coincide to 2 significant digits (state labels would collide)")
    return Protocol(sorted(dphi) if dphi else None, sorted(pressure) if pressure else None,
                    ladder, ftol, tuple(window), phi_start, phic_method)


def _solver(raw, path):
    t = _Table(raw, "solver", path)
    out = {"tol": t.float("tol", 1e-10, lo=0.0, hi=1e-2, lo_open=True),
           "dense_max_dof": t.int("dense_max_dof", DENSE_MAX_DOF, lo=1, hi=40_000),
           "small_dof": t.int("small_dof", SMALL_DOF, lo=0)}
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
            t.fail("at", f"must list \"phi_c\" or protocol values, got {v!r}")
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
    return _Table(raw, f"observables.{name}", path)


def _observables(raw, path, systems, protocol):
    if raw is None:
        raise ParjamError(f"{path}: no [observables] table: nothing to compute")
    top = _Table(raw, "observables", path)
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
    from parjam import softmodes as sm

    cuts = t.strings("cuts", None)
    sub = t.int("subdivide", None, lo=1, hi=1000)
    if cuts is None and sub is None:
        cuts = ["x=0.5"]
    for c in cuts or []:
        try:
            sm.parse_cut(c, 3)
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


# --------------------------------------------------------------------------- the plan

@dataclass
class Stage:
    """One unit of work for one system, done member by member (or once, for the summary)."""

    kind: str  # pack | network | spectrum | moduli | softmodes | fluctuations | summary
    system: System
    params: dict  # what the stage computes; for spectra: per-state requirements and solver
    deps: list  # keys of the stages it reads
    states: list = field(default_factory=list)
    matrix: str = None
    key: str = ""
    memory_mb: float = 0.0
    seconds: float = 0.0

    @property
    def name(self):
        tag = f"{self.kind}-{self.matrix}" if self.matrix else self.kind
        return f"{tag}-{self.system.name}-{self.key}"

    def solvers(self):
        if self.kind != "spectrum":
            search = ("phi_c extrapolated from above"
                      if self.params.get("phic_method") == "extrapolate" else "O'Hern bisection")
            return {"pack": f"FIRE + Newton (MUMPS), {search}", "network": "numpy",
                    "moduli": "PETSc CG + MUMPS",
                    "softmodes": "MUMPS inertia + block inverse iteration",
                    "fluctuations": "numpy", "summary": "numpy"}.get(self.kind, "")
        return {s: self.params[s]["solver"] for s in self.states}


STAGE_FORMAT = 1  # bump when a stage's stored content changes: old results are then recomputed


def stage_key(*parts):
    blob = json.dumps([STAGE_FORMAT, parts], sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:12]


def spectrum_needs(scene, system):
    """Per (matrix, state): what the observables need of that spectrum."""
    need = {}

    def want(matrix, state, **kw):
        d = need.setdefault(matrix, {}).setdefault(
            state, {"all": False, "k": 0, "window": None, "per_mode": False, "vectors": False})
        if kw.get("kpm_plateau"):
            d["kpm_plateau"] = True  # only when asked: the other stage keys stay as they were
        d["all"] |= kw.get("all", False)
        d["k"] = max(d["k"], kw.get("k") or 0)
        d["per_mode"] |= kw.get("per_mode", False)
        d["vectors"] |= kw.get("vectors", False)
        if kw.get("window") is not None:
            w = kw["window"]
            d["window"] = w if d["window"] is None else (min(d["window"][0], w[0]),
                                                         max(d["window"][1], w[1]))

    obs = scene.observables
    if "dos" in obs:
        o = obs["dos"]
        for m in o["matrices"]:
            for s in o["at"]:
                want(m, s, all=o["window"] is None, window=o["window"])
    if "omega_star" in obs:
        o = obs["omega_star"]
        for m in o["matrices"]:
            for s in o["at"]:
                want(m, s, all=o["window"] is None and o["k"] is None, window=o["window"],
                     k=o["k"], kpm_plateau=o["plateau"] == "kpm")
    if "lowest" in obs:
        o = obs["lowest"]
        for m in o["matrices"]:
            for s in o["at"]:
                want(m, s, k=o["k"], vectors=o["vectors"])
    if "trans" in obs:
        o = obs["trans"]
        for s in o["at"]:
            want(o["matrix"], s, all=o["k"] is None, k=o["k"], per_mode=True)
    return need


def choose_solver(req, system, solver):
    """The cheapest solver that gives what the state needs (see the module doc)."""
    dof = system.max_dof
    if req["all"]:
        if dof > solver["dense_max_dof"]:
            raise ParjamError(
                f"system {system.name}: the whole spectrum of {dof} degrees of freedom exceeds "
                f"solver.dense_max_dof = {solver['dense_max_dof']}: give a window or k")
        return "dense-eigh" if req["per_mode"] or req["vectors"] else "dense-eigvalsh"
    if req["window"] is not None and req["k"]:
        return "dense-eigh" if dof <= solver["small_dof"] else "slice+sinvert"
    if req["window"] is not None:
        return "dense-eigh" if dof <= solver["small_dof"] else "slice"
    return "dense-eigh" if dof <= solver["small_dof"] else "sinvert"


def estimate(stage, scene):
    """Rough memory (MB, per rank) and time (s, one core, all members) of a stage."""
    s, members = stage.system, scene.members
    n, dof = s.n, s.max_dof
    nstates = len(stage.states) or 1
    if stage.kind == "pack":
        # measured on this machine: 3D N = 512 full ladder 10-25 s, 2D N = 1024 ~80 s
        per = 0.04 * n ** 1.1 * (3.0 if s.d == 2 else 1.0) * (1 + 0.15 * nstates)
        if stage.params.get("phic_method") == "extrapolate":
            per *= 0.4  # measured: 3D N = 10240, five states, 710 s per member (2 ranks busy)
        return 50 + n * 2e-3, members * per
    if stage.kind == "spectrum":
        mem, sec = 0.0, 0.0
        for st in stage.states:
            sol = stage.params[st]["solver"]
            if sol.startswith("dense"):
                mem = max(mem, 3 * 8 * dof * dof / 1e6)
                # measured: eigvalsh of 3000 x 3000 in 3.2 s on one core, eigh 7.7 s
                sec += 0.12 * (dof / 1000.0) ** 3 * (1.0 if sol == "dense-eigvalsh" else 4.0)
            else:
                k = max(stage.params[st]["k"], 50)
                mem = max(mem, 8 * dof * (k * 2 + 300) / 1e6)
                sec += 1e-4 * dof ** 1.3 + 1e-3 * k * dof / 100
        return 50 + mem, members * sec
    if stage.kind == "moduli":
        return 50 + 8 * dof * 300 / 1e6, members * nstates * (1e-3 * dof ** 1.2)
    if stage.kind == "softmodes":
        return 50 + 8 * dof * dof ** (2 / 3) * 2 / 1e6, members * nstates * 3e-4 * dof ** 1.4
    return 50.0, members * nstates * 1e-4 * n


def plan(scene):
    """The stages of a scene, in order, each keyed by a hash of its inputs."""
    stages = []
    obs = scene.observables
    for s in scene.systems:
        base = {"system": s.key(), "protocol": scene.protocol.key(), "seed": scene.seed}
        pack = Stage("pack", s, {"labels": scene.protocol.labels(),
                                 "phic_method": scene.protocol.phic_method}, [],
                     scene.protocol.labels())
        pack.key = stage_key("pack", base)
        net = Stage("network", s, {}, [pack.key], scene.protocol.labels())
        net.key = stage_key("network", pack.key)
        mine = [pack, net]
        for matrix, per_state in sorted(spectrum_needs(scene, s).items()):
            params = {}
            for st, req in per_state.items():
                params[st] = dict(req, solver=choose_solver(req, s, scene.solver))
            states = [lab for lab in scene.protocol.labels() if lab in params]
            sp = Stage("spectrum", s, params, [pack.key], states, matrix)
            sp.key = stage_key("spectrum", matrix, pack.key, params, scene.solver["tol"])
            mine.append(sp)
        for kind in ("moduli", "softmodes", "fluctuations"):
            if kind in obs:
                o = {k: v for k, v in obs[kind].items() if k != "at"}
                st = Stage(kind, s, o, [pack.key], obs[kind]["at"])
                st.key = stage_key(kind, pack.key, o, st.states)
                mine.append(st)
        summ = Stage("summary", s, {"observables": obs, "members": scene.members},
                     [x.key for x in mine], scene.protocol.labels())
        summ.key = stage_key("summary", summ.deps, obs, scene.members)
        mine.append(summ)
        for st in mine:
            st.memory_mb, st.seconds = estimate(st, scene)
        stages += mine
    return stages


def describe(scene, stages):
    """The --dry-run text: stages, sizes, solver per stage, estimated memory and time."""
    lines = [f"scene {scene.name!r}: {len(scene.systems)} system(s), {scene.members} member(s), "
             f"seed {scene.seed}; states {', '.join(scene.protocol.labels())}"
             + (f" ({scene.protocol.ladder})" if scene.protocol.dphi else ""),
             f"observables: {', '.join(scene.observables)}"]
    total = 0.0
    for st in stages:
        s = st.system
        head = f"  {st.kind + (' ' + st.matrix if st.matrix else ''):<17} {s.name:<22} " \
               f"d={s.d} N={s.n} alpha={s.alpha:g}  key {st.key}"
        lines.append(head)
        if st.kind == "spectrum":
            for state in st.states:
                p = st.params[state]
                what = ("all modes" if p["all"] else
                        f"window {p['window']}" if p["window"] else f"lowest k={p['k']}")
                extra = ", per-mode sums" if p["per_mode"] else ""
                extra += ", eigenvectors stored" if p["vectors"] else ""
                extra += ", D0 from KPM" if p.get("kpm_plateau") and not p["all"] else ""
                lines.append(f"      {state:<12} {what}{extra}: {p['solver']}")
        else:
            lines.append(f"      states {', '.join(st.states)}; {st.solvers()}")
        lines.append(f"      estimate: {st.memory_mb:.0f} MB per rank, {st.seconds:.0f} s of "
                     f"one core")
        total += st.seconds
    lines.append(f"total estimate: {total:.0f} s of one core "
                 f"({total / 60:.1f} min; divide by the ranks for members spread over them)")
    return "\n".join(lines)
