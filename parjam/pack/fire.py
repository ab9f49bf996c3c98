"""FIRE (Bitzek et al., PRL 97, 170201 (2006)) to a force tolerance, one fused compiled step per
iteration on the spatial decomposition (parjam.pack.engine.SlabEngine.step: update, ghost refresh,
forces and partial sums, then one allreduce of the exact sums), with the choice of today's
parameters or FIRE 2.0 (Guenole et al., Comput. Mater. Sci. 175, 109584 (2020), Algorithm 2 and
Table 1).

The trajectory is the same bits on any number of ranks: the force on a particle is summed over
its pairs in global (i, j) order, and the sums FIRE decides on (energy, F.v, |F|^2, |v|^2, the
maxima) are exact (parjam.net.exactsum) -- so neither the slabs, nor when the neighbour lists are
rebuilt, nor where a run was checkpointed and resumed, changes a bit.

Both variants integrate with semi-implicit Euler (v += dt F, then x += dt v) and step half back
(x -= dt v / 2, v = 0) when the power P = F.v turns non-positive.  FIRE 2.0 differs in its
parameters and in the "initial delay": during the first n_delay steps an uphill step does not
shrink dt nor reset the mixing, and dt never drops below dt_min (a shrink that would is skipped).
"""

from dataclasses import dataclass

import numpy as np


@dataclass
class FireParams:
    dt: float = 0.05
    dt_max: float = 0.5
    dt_min: float = 1e-4
    n_delay: int = 5
    f_inc: float = 1.1
    f_dec: float = 0.5
    a0: float = 0.1
    f_a: float = 0.99
    max_steps: int = 200000
    variant: str = "fire"  # "fire" or "fire2" (FIRE 2.0's initial delay and dt_min rule)

    @classmethod
    def fire2(cls, dt=0.05, **kw):
        """FIRE 2.0 with the paper's Table 1 values: dt_max = 10 dt, dt_min = 0.02 dt,
        N_delay = 20, alpha_start = 0.25, f_alpha = 0.99, f_inc = 1.1, f_dec = 0.5."""
        base = dict(dt=dt, dt_max=10 * dt, dt_min=0.02 * dt, n_delay=20, a0=0.25, f_a=0.99,
                    f_inc=1.1, f_dec=0.5, variant="fire2")
        base.update(kw)
        return cls(**base)


VARIANTS = ("fire", "fire2")
# the variant minimize() uses when not told otherwise (docs/explanation/scaling.md, "FIRE 2.0")
DEFAULT_VARIANT = "fire"


def params_for(variant=None, **kw):
    """FireParams of a variant by name ("fire": today's values, "fire2": FIRE 2.0's; None:
    DEFAULT_VARIANT)."""
    variant = DEFAULT_VARIANT if variant is None else variant
    if variant == "fire2":
        return FireParams.fire2(**kw)
    if variant == "fire":
        return FireParams(**kw)
    raise ValueError(f"unknown FIRE variant {variant!r} (choose from {', '.join(VARIANTS)})")


@dataclass
class MinResult:
    status: str  # "converged", "unjammed" or "not converged"
    energy: float
    fmax: float
    fire_steps: int = 0
    newton_steps: int = 0

    @property
    def ok(self):
        return self.status == "converged"


@dataclass
class FireState:
    """FIRE's dynamical state besides the positions: enough to continue a run exactly."""

    v: np.ndarray  # velocities of this rank's block rows [ff.lo, ff.hi), (hi - lo, d)
    dt: float
    a: float
    n_pos: int
    step: int


SNAPSHOT_EVERY = 100  # FIRE steps between offers of a snapshot (see ``fire``)


def control(p, power, step, dt, a, n_pos):
    """FIRE's decision at step ``step`` (1-based) from the power P = F.v: returns (reset, dt,
    a, n_pos), reset meaning "step half back and stop" (P <= 0).  Downhill, dt grows by f_inc
    and the mixing a shrinks by f_a once n_delay steps in a row were downhill.  Uphill, plain
    FIRE halves dt (not below dt_min) and resets a; FIRE 2.0 does neither during the first
    n_delay steps (initial delay) and skips a shrink that would take dt below dt_min."""
    if power > 0.0:
        n_pos += 1
        if n_pos > p.n_delay:
            dt = min(dt * p.f_inc, p.dt_max)
            a *= p.f_a
        return False, dt, a, n_pos
    if p.variant != "fire2":
        dt = max(dt * p.f_dec, p.dt_min)
        a = p.a0
    elif step >= p.n_delay:
        if dt * p.f_dec >= p.dt_min:
            dt *= p.f_dec
        a = p.a0
    return True, dt, a, 0


def fire(ff, ftol, e_stop=-np.inf, params=None, progress=None, start=None, snapshot=None):
    """FIRE on ff's positions until max|F| < ftol, or the energy falls below e_stop
    (-> "unjammed"), on the spatial decomposition: ``ff.start_engine()`` (parjam.pack.engine) holds
    each rank's slab of particles, a step is one compiled update + ghost refresh + forces and
    one allreduce, and the positions return to ff.x at the end.

    ``start`` (a FireState) continues an interrupted run from its velocities (this rank's
    block rows), time step and counters.  Every SNAPSHOT_EVERY steps ``snapshot(make_state)``
    is called, if given, on all ranks; ``make_state()`` (collective) returns the current
    FireState, its velocities handed from the engine's rows to the block rows (no rank gathers
    all N; parjam.files.checkpoint writes them by row blocks).  A run resumed from it, on any
    number of ranks, goes on bitwise as the uninterrupted one: the forces and the sums depend on
    the positions and velocities only, not on the decomposition."""
    p = params or FireParams()
    dt, a, n_pos, step = p.dt, p.a0, 0, 0
    v0 = None
    if start is not None:
        v0 = np.array(start.v, dtype=np.float64)
        dt, a, n_pos, step = start.dt, start.a, start.n_pos, start.step
    eng = ff.start_engine(v0)
    ff.n_force_calls += 1
    s = eng.start()
    status = "not converged"

    def make_state():
        return FireState(ff.block_rows(eng.v), dt, a, n_pos, step)

    stops_on_energy = e_stop > -np.inf
    for step in range(step + 1, p.max_steps + 1):
        if s.energy < e_stop:
            status = "unjammed"
            break
        if s.fmax < ftol:
            status = "converged"
            break
        reset, dt, a, n_pos = control(p, s.power, step, dt, a, n_pos)
        # semi-implicit Euler with FIRE mixing (unit masses): v' = v + dt F (v = 0 after the
        # half step back), |v'|^2 = |v|^2 + 2 dt P + dt^2 |F|^2 from the last reduction
        vn2 = dt * dt * s.f2 if reset else s.v2 + 2.0 * dt * s.power + dt * dt * s.f2
        fn = np.sqrt(s.f2)
        mix_v, mix_f = (1.0 - a, a * np.sqrt(vn2) / fn) if fn > 0.0 else (1.0, 0.0)
        ff.n_force_calls += 1
        # the energy only where a decision or a line needs it (it costs 5 - 6 % of a step)
        shown = progress is not None and step % 100 == 0
        s = eng.step(dt, reset, mix_v, mix_f, s, energy=stops_on_energy or shown)
        if shown:
            progress(f"FIRE step {step}: E/N = {s.energy / ff.n:.3e}, max|F| = {s.fmax:.3e}")
        if snapshot is not None and step % SNAPSHOT_EVERY == 0:
            snapshot(make_state)
    if np.isnan(s.energy) and not np.isnan(s.fmax):  # the last step's, with its energy
        s = eng.start()  # the same positions: the same forces and sums, bit for bit
    ff.stop_engine()
    ff.wrap()
    return MinResult(status, s.energy, s.fmax, fire_steps=step)


def fire_unfused(ff, ftol, params=None, max_steps=None):
    """The same FIRE as ``fire`` (no snapshots, no e_stop) step by step in PETSc Vec operations
    and separate reductions (three dots/norms, a max-norm, the energy), as parjam ran it before
    the fused step: the reference the fused step is tested and benchmarked against
    (tests/pack/test_fire.py).  Returns (MinResult, steps)."""
    p = params or FireParams()
    f, v = ff.vec(), ff.vec()
    v.set(0.0)
    energy = ff.evaluate(f)
    fmax = ff.max_norm(f)
    dt, a, n_pos, step = p.dt, p.a0, 0, 0
    status = "not converged"
    for step in range(1, (max_steps or p.max_steps) + 1):
        if fmax < ftol:
            status = "converged"
            break
        reset, dt, a, n_pos = control(p, f.dot(v), step, dt, a, n_pos)
        if reset:
            ff.x.axpy(-0.5 * dt, v)
            v.set(0.0)
        v.axpy(dt, f)
        vn, fn = v.norm(), f.norm()
        if fn > 0.0:
            v.axpby(a * vn / fn, 1.0 - a, f)
        ff.x.axpy(dt, v)
        energy = ff.evaluate(f)
        fmax = ff.max_norm(f)
    for vec in (f, v):
        vec.destroy()
    return MinResult(status, energy, fmax, fire_steps=step)
