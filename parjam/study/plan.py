"""The plan of a scene (parjam.study.scene): the stages its observables need, each keyed by a
hash of its inputs, with the solver per spectrum and rough estimates (``--dry-run``).

:func:`plan` computes only what the observables need:

- ``pack``: the packings of every member (always);
- ``network``: z, dz, p of every state (always: cheap, and the other stages report them);
- ``spectrum`` per matrix (full / relaxed / stress): only for the states and matrices an
  observable asks for; the solver per state follows from what is needed there:
  the whole spectrum (D(omega), omega* without a window) -> dense LAPACK, eigenvalues only unless
  per-mode sums are wanted; a window -> SLEPc slicing; the k lowest modes -> SLEPc
  shift-and-invert, by the policy of parjam.vib.solver_choice (dense for windows and k up to
  ``solver.small_dof``).  No relaxed matrix unless asked for, no
  eigenvectors stored unless ``lowest.vectors``;
- ``moduli``, ``softmodes``, ``fluctuations`` only when asked for;
- ``summary``: ensemble means, errors and D(omega) averages of everything computed.
"""

import hashlib
import json
from dataclasses import dataclass, field

from parjam import resources
from parjam.vib import kpm_dos, solver_choice
from parjam.errors import ParjamError
from parjam.files import inputs
from parjam.study.scene import System

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
        if kw.get("kpm"):
            d["kpm"] = kw["kpm"]  # D(omega) by KPM (parjam.vib.kpm_dos), likewise only when asked
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
        kpm = ({q: o[q] for q in ("moments", "probes", "max_moments")}
               if o.get("method") == "kpm" else None)
        for m in o["matrices"]:
            for s in o["at"]:
                if kpm:
                    want(m, s, kpm=kpm)
                else:
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
    """The solver of one state's spectrum by the one policy (parjam.vib.solver_choice), with the
    scene's [solver] limits; a dense solve is "dense-eigvalsh" (eigenvalues only) unless
    per-mode sums or vectors are wanted."""
    dof = system.max_dof
    if req.get("kpm") and not (req["all"] or req["k"] or req["window"] is not None):
        return "kpm"  # D(omega), D0 and omega* from KPM moments alone (parjam.vib.kpm_dos)
    limits = solver_choice.Limits(whole_max_dof=solver["dense_max_dof"],
                                  partial_dense_max_dof=solver["small_dof"])
    try:
        sol = solver_choice.choose_solver(dof, dof - system.d, k=req["k"] or None,
                                          window=req["window"], whole=req["all"],
                                          tol=solver["tol"], limits=limits)
    except ParjamError:
        raise ParjamError(
            f"system {system.name}: the whole spectrum of {dof} degrees of freedom exceeds "
            f"solver.dense_max_dof = {solver['dense_max_dof']}: give a window or k") from None
    if sol != "dense":
        return sol
    return "dense-eigvalsh" if req["all"] and not (req["per_mode"] or req["vectors"]) \
        else "dense-eigh"


# Time models of the partial spectra and of KPM, one core (docs/results/reproduction.md, section 11):
# shift-and-invert of the k lowest modes ~ factorisation + k solves and orthogonalisations,
# fitted to 4.5 s at 12273 dof, k = 50 (docs/results/speed-accuracy.md) and 140 s at 30720 dof, k = 1000
# (N = 10240, docs/results/reproduction.md section 10); KPM = (probes x moments / 2 + 40 Lanczos)
# products of 0.45 - 0.8 ms at 30720 dof (N = 10240, 4096 moments x 4 probes in 4 - 7 s) +
# evaluating the cumulative on a 4 M grid while the moments double (parjam.vib.kpm_dos).  Checked
# at N = 10240 (section 11): 167 s of CPU per member measured against 205 s estimated.
SINVERT_FACTOR = 1.4e-6
SINVERT_PER_MODE = 4.3e-6
KPM_MATVEC = 2.5e-8
KPM_EVAL = 5e-8
KPM_DELTA_OMEGA = 4.0  # (pi/2) sqrt(lambda_max) of 3D harmonic spheres, dphi <= 1e-2 (measured)


def kpm_moments_guess(opts, label):
    """The moments KPM will use at a state: the given number, or for "auto" the resolution
    rule of parjam.vib.kpm_dos with omega* ~ 1.6 dphi^(1/2) (3D harmonic spheres, measured at
    N = 1024 and 10240) and Delta omega ~ KPM_DELTA_OMEGA / M; the cap for target pressures."""
    if opts["moments"] != "auto":
        return opts["moments"]
    if not label.startswith("dphi"):
        return opts["max_moments"]
    wstar = 1.6 * float(label[4:]) ** 0.5
    m = kpm_dos.AUTO_START
    while m < opts["max_moments"] and wstar < kpm_dos.RESOLVED * KPM_DELTA_OMEGA / m:
        m *= 2
    return min(m, opts["max_moments"])


def estimate(stage, scene):
    """Rough memory (MB, per rank) and time (s, one core, all members) of a stage."""
    s, members = stage.system, scene.members
    n, dof = s.n, s.max_dof
    nstates = len(stage.states) or 1
    if stage.kind == "pack":  # the models `parjam pack` checks itself against
        per = resources.pack_seconds(s.d, n, nstates,
                                     stage.params.get("phic_method") or "bisect")
        return resources.pack_memory_mb(n, s.d), members * per
    if stage.kind == "spectrum":
        mem, sec = 0.0, 0.0
        for st in stage.states:
            sol = stage.params[st]["solver"]
            if sol.startswith("dense"):
                # measured: N = 1024 (dof 3057), eigh of 3000 modes with the per-mode
                # observables, peak RSS 525 MB (the matrix, its deflated copy, LAPACK's copy,
                # the vectors and the workspace: ~6 dof^2 doubles)
                mem = max(mem, 6 * 8 * dof * dof / 1e6)
                # measured: eigvalsh of 3000 x 3000 in 3.2 s on one core, eigh 7.7 s
                sec += 0.12 * (dof / 1000.0) ** 3 * (1.0 if sol == "dense-eigvalsh" else 4.0)
            elif sol != "kpm":
                k = max(stage.params[st]["k"], 50)
                # Lanczos basis and vectors, plus the MUMPS factor: 6.3e6 entries at 12273 dof
                # (docs/results/speed-accuracy.md), growing as dof^(4/3) in 3D, ~12 bytes an entry;
                # measured at N = 10240, k = 400: peak RSS 737 MB per rank, estimate 560 MB
                mem = max(mem, 8 * dof * (k * 2 + 300) / 1e6 + 260 * dof ** (4 / 3) / 1e6)
                sec += SINVERT_FACTOR * dof ** 1.5 + SINVERT_PER_MODE * k * dof
            if stage.params[st].get("kpm"):
                o = stage.params[st]["kpm"]
                m = kpm_moments_guess(o, st)
                mem = max(mem, 8 * dof * (3 * o["probes"] + 4) / 1e6 + 8 * 40 * dof * 2 / 1e6)
                sec += KPM_MATVEC * dof * (o["probes"] * m / 2 + 40) + KPM_EVAL * m * m
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


def machine_need(scene, stages, ranks, ranks_on_node):
    """(largest memory per rank in MB, wall seconds, ranks on this node) of a plan: the stages
    run one after another, their members spread over the ranks (checked against the machine by
    parjam.resources)."""
    spread = max(min(scene.members, ranks), 1)
    memory = max((st.memory_mb for st in stages), default=0.0)
    return memory, sum(st.seconds for st in stages) / spread, ranks_on_node


def describe(scene, stages):
    """The --dry-run text: stages, sizes, solver per stage, estimated memory and time."""
    lines = [f"scene {scene.name!r}: {len(scene.systems)} system(s), {scene.members} member(s), "
             f"seed {scene.seed}; states {', '.join(scene.protocol.labels())}"
             + (f" ({scene.protocol.ladder})" if scene.protocol.dphi else ""),
             f"observables: {', '.join(scene.observables)}"]
    renamed = [(what, title, name) for what, title, name in
               [("scene", scene.title, scene.name)]
               + [("system", s.title, s.name) for s in scene.systems] if title]
    for what, title, name in renamed:  # names from user text are one path component
        lines.append(f"{what} {inputs.shown(repr(title))} names its files {name!r}")
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
                if p.get("kpm"):
                    what += " + KPM" if p["all"] or p["window"] or p["k"] else ""
                    what = "KPM" if p["solver"] == "kpm" else what
                    extra += f", {p['kpm']['moments']} moments x {p['kpm']['probes']} probes"
                lines.append(f"      {state:<12} {what}{extra}: {p['solver']}")
        else:
            lines.append(f"      states {', '.join(st.states)}; {st.solvers()}")
        lines.append(f"      estimate: {st.memory_mb:.0f} MB per rank, {st.seconds:.0f} s of "
                     f"one core")
        total += st.seconds
    lines.append(f"total estimate: {total:.0f} s of one core "
                 f"({total / 60:.1f} min; divide by the ranks for members spread over them)")
    return "\n".join(lines)
