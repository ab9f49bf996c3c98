"""The fused FIRE step (parjam.pack.fire, parjam_fire_step in _kernels.c) against the step-by-step
PETSc FIRE it replaced, FIRE 2.0's rules, and the numpy fallback of the kernels."""

import numpy as np
import pytest

from parjam import env
from parjam.pack import kernels
from parjam.pack.engine import SlabEngine
from parjam.pack.fire import FireParams, control, fire, fire_unfused
from parjam.pack.forces import ForceField
from parjam.pack.packing import random_packing
from parjam.net.system import neighbour_pairs
from parjam.testing.gather import gather, gather_engine


def _run(comm, pack, fn, params):
    ff = ForceField(comm, pack.diam, pack.L, pack.d, pack.alpha)
    ff.set_positions(pack.pos)
    res = fn(ff, 0.0, params=params)
    pos = np.array(gather(ff))
    rebuilds = ff.n_rebuilds  # collective: the same on every rank
    ff.destroy()
    return res, pos, rebuilds


def _dist(a, b, L):
    d = a - b
    return np.abs(d - L * np.rint(d / L)).max()


@pytest.mark.parametrize("d, alpha, variant", [(3, 2.0, "fire"), (2, 2.5, "fire"),
                                               (3, 2.0, "fire2"), (2, 2.0, "fire2")])
def test_fused_step_follows_the_unfused_fire(world, d, alpha, variant):
    """250 fused steps from a random (overlapping, far from balance) state land where the
    step-by-step PETSc FIRE lands, to round-off, on one rank and on all ranks; a fused run on
    all ranks equals one on one rank as strictly.  Both pass through many neighbour rebuilds and
    uphill resets, so a wrong mixing, reset or stale list would show at O(skin)."""
    PETSc = env.petsc()
    pack = random_packing(d, 300, 0.9 if d == 2 else 0.7, alpha, "bi", 1.4,
                          np.random.default_rng(7))
    params = FireParams(max_steps=250) if variant == "fire" else FireParams.fire2(max_steps=250)
    fused_self, pos_self, reb_self = _run(PETSc.COMM_SELF, pack, fire, params)
    fused_world, pos_world, reb_world = _run(world, pack, fire, params)
    plain, pos_plain, reb_plain = _run(world, pack, fire_unfused, params)
    assert reb_plain > 5 and reb_self == reb_plain  # one rank: the same rebuild rule as before
    assert reb_world == reb_plain  # several ranks: the same rule (the exact displacement)
    assert fused_self.fire_steps == plain.fire_steps == 250
    scale = pack.diam.min()
    assert _dist(pos_self, pos_plain, pack.L) < 1e-9 * scale
    assert _dist(pos_world, pos_self, pack.L) < 1e-9 * scale
    assert fused_self.energy == pytest.approx(plain.energy, rel=1e-9)
    assert fused_world.fmax == pytest.approx(fused_self.fmax, rel=1e-6)
    # and the run moved far: the comparisons above are not of a state that stayed put
    assert _dist(pos_self, pack.pos, pack.L) > 2 * 0.2 * pack.diam.min()  # > 2 skins


def test_fused_step_is_one_semi_implicit_euler_step_with_mixing(world):
    """One fused step against the FIRE update written out in numpy (dense reference), for an
    uphill reset and a downhill step, with the forces at the new positions."""
    PETSc = env.petsc()
    pack = random_packing(3, 200, 0.68, 2.0, "bi", 1.4, np.random.default_rng(3))
    rng = np.random.default_rng(1)
    v0 = 1e-3 * rng.standard_normal(pack.pos.shape)
    ref = ForceField(PETSc.COMM_SELF, pack.diam, pack.L, 3, 2.0)
    ref.set_positions(pack.pos)
    fref = ref.vec()
    ref.evaluate(fref)
    f0 = np.array(ref.local(fref))
    for reset in (False, True):
        dt, mix_v, mix_f = 0.07, 0.9, 0.3
        ff = ForceField(world, pack.diam, pack.L, 3, 2.0)
        ff.set_positions(pack.pos)
        eng = ff.start_engine(v0[ff.lo:ff.hi])
        s0 = eng.start()
        assert s0.power == pytest.approx(np.vdot(f0, v0), rel=1e-10)
        assert s0.f2 == pytest.approx(np.vdot(f0, f0), rel=1e-12)
        assert s0.fmax == pytest.approx(np.sqrt((f0**2).sum(1)).max(), rel=1e-14)
        assert s0.vmax == pytest.approx(np.sqrt((v0**2).sum(1)).max(), rel=1e-14)
        s = eng.step(dt, reset, mix_v, mix_f, s0)
        x, vv = pack.pos.copy(), v0.copy()
        if reset:
            x -= 0.5 * dt * vv
            vv[:] = 0.0
        vv = mix_f * f0 + mix_v * (vv + dt * f0)
        x += dt * vv
        np.testing.assert_allclose(gather_engine(ff, eng.v), vv, rtol=0, atol=1e-15)
        np.testing.assert_allclose(gather(ff), x, rtol=0, atol=1e-13)
        ref.set_positions(x)
        e1 = ref.evaluate(fref)
        np.testing.assert_allclose(gather_engine(ff, eng.f), ref.local(fref), rtol=0,
                                   atol=1e-13 * np.abs(f0).max())
        assert s.energy == pytest.approx(e1, rel=1e-12)
        assert s.disp == pytest.approx(np.sqrt(((x - pack.pos) ** 2).sum(1)).max(), rel=1e-9)
        ff.stop_engine()
        ff.destroy()
    fref.destroy()
    ref.destroy()


def test_energy_summed_only_where_asked_changes_nothing(world):
    """FIRE sums the energy only where a stop on it or a progress line needs it, and once at
    the end: a run without them ends bitwise where a run that sums it every step (a stopping
    energy that never stops it) ends, with the same energy; a step not asked for the energy
    reports NaN and the same other sums."""
    pack = random_packing(3, 400, 0.7, 2.0, "bi", 1.4, np.random.default_rng(5))
    params = FireParams(max_steps=300)
    lean, pos_lean, _ = _run(world, pack, fire, params)
    lines = []

    def every_step(ff, ftol, params):
        return fire(ff, ftol, e_stop=-1e300, params=params, progress=lines.append)

    full, pos_full, _ = _run(world, pack, every_step, params)
    assert len(lines) == 3 and lean.fire_steps == full.fire_steps == 300
    np.testing.assert_array_equal(pos_lean, pos_full)
    assert lean.energy == full.energy > 0.0 and lean.fmax == full.fmax
    mine = np.arange(world.rank, pack.n, world.size)

    def engine():
        return SlabEngine(world, pack.L, 2.0, 1.0, 0.2, pack.pos[mine], mine, pack.diam[mine])

    eng = engine()
    with_e = eng.step(0.02, False, 0.9, 0.05, eng.start(), energy=True)
    eng = engine()
    without = eng.step(0.02, False, 0.9, 0.05, eng.start(energy=False), energy=False)
    assert np.isnan(without.energy) and with_e.energy > 0.0
    for name in ("power", "f2", "v2", "fmax", "vmax", "disp"):
        assert getattr(without, name) == getattr(with_e, name)


def test_fire2_rules_initial_delay_and_dt_min():
    """FIRE's decisions (parjam.pack.fire.control): downhill growth after n_delay steps, and uphill
    plain FIRE halves dt and resets a at once, FIRE 2.0 not during its initial delay, and never
    below dt_min (where plain FIRE clamps to it)."""
    plain, f2 = FireParams(), FireParams.fire2(dt=0.1)
    assert (f2.dt_max, f2.dt_min, f2.n_delay, f2.a0) == (1.0, 0.002, 20, 0.25)
    # downhill: nothing changes during the delay, then dt * f_inc and a * f_a
    reset, dt, a, n = control(f2, 1.0, 30, 0.1, 0.2, 20)
    assert (reset, n) == (False, 21) and dt == pytest.approx(0.11) and a == pytest.approx(0.198)
    assert control(f2, 1.0, 30, 0.1, 0.2, 3) == (False, 0.1, 0.2, 4)
    assert control(f2, 1.0, 30, 0.99, 0.2, 30)[1] == 1.0  # capped at dt_max
    # uphill inside the initial delay: FIRE 2.0 keeps dt and a, plain FIRE does not
    assert control(f2, -1.0, 5, 0.1, 0.2, 7) == (True, 0.1, 0.2, 0)
    assert control(plain, -1.0, 5, 0.1, 0.05, 7) == (True, 0.05, 0.1, 0)
    assert control(f2, 0.0, 25, 0.1, 0.2, 7) == (True, 0.05, 0.25, 0)  # P = 0 counts as uphill
    # dt_min: FIRE 2.0 skips a shrink below it, plain FIRE clamps
    assert control(f2, -1.0, 25, 0.003, 0.2, 0) == (True, 0.003, 0.25, 0)
    assert control(plain, -1.0, 25, 1.5e-4, 0.2, 0) == (True, 1e-4, 0.1, 0)


@pytest.mark.parametrize("d,alpha", [(3, 2.5), (2, 2.5), (3, 2.0), (2, 2.0), (3, 3.0), (2, 1.5)])
def test_numpy_fallback_warns_once_and_gives_the_same_forces(d, alpha, monkeypatch, capsys):
    """With PARJAM_KERNELS=numpy the kernels fall back to numpy, say so once on stderr, and the
    forces, energy and fused step agree with the compiled ones to round-off -- for each of the
    compiled loops: harmonic, Hertz (delta sqrt(delta) for delta^1.5) and any alpha (pow), in
    2D and 3D."""
    if kernels.library() is None:
        pytest.fail("the compiled kernels are not available (a C compiler is part of the setup)")
    pack = random_packing(d, 300, 0.7 if d == 3 else 0.88, alpha, "poly", 1.3,
                          np.random.default_rng(8))
    pairs = neighbour_pairs(pack.pos, pack.L, pack.diam.max() * 1.2)
    pi, pj = np.ascontiguousarray(pairs[:, 0]), np.ascontiguousarray(pairs[:, 1])
    v0 = 1e-2 * np.random.default_rng(2).standard_normal(pack.pos.shape)

    def compute():
        out = np.zeros_like(pack.pos)
        e = kernels.pair_forces(pi, pj, pack.pos, pack.diam, pack.L, alpha, 1.0, 0, pack.n, out)
        x, v, f = pack.pos.copy(), v0.copy(), out.copy()
        acc = np.zeros(kernels.FIRE_ACC, dtype=np.int64)
        kernels.fire_step(kernels.FIRE_UPDATE | kernels.FIRE_FORCES | kernels.FIRE_ENERGY, x,
                          v, f, pack.pos, pack.L,
                          0.05, False, -0.025, 0.9, 0.2, 0.0, pi, pj, x, pack.diam, alpha, 1.0,
                          0, pack.n, acc)
        return e, out, x, f, kernels.fire_sums(acc)

    compiled = compute()
    assert "numpy" not in capsys.readouterr().err
    monkeypatch.setenv("PARJAM_KERNELS", "numpy")
    kernels.reset()
    try:
        assert kernels.library() is None
        fallback = compute()
        fallback_again = compute()
        err = capsys.readouterr().err
    finally:
        monkeypatch.delenv("PARJAM_KERNELS")
        kernels.reset()
    from mpi4py import MPI

    if MPI.COMM_WORLD.Get_rank() == 0:  # one line, once, on rank 0 only
        assert err.count("warning") == 1 and "numpy" in err and len(err.strip().splitlines()) == 1
    else:
        assert err == ""
    assert kernels.library() is not None
    for c, n, m in zip(compiled, fallback, fallback_again):
        np.testing.assert_allclose(c, n, rtol=1e-12, atol=1e-15 * np.abs(n).max())
        np.testing.assert_array_equal(n, m)


def test_library_is_built_from_this_source(tmp_path):
    """The compiled library (built at install time by setup.py, or on first use into the cache)
    carries the SHA-256 of the _kernels.c it was built from; the one in use matches the source,
    and compile_library makes one that does."""
    import ctypes

    lib = kernels.library()
    if lib is None:
        pytest.fail("the compiled kernels are not available (a C compiler is part of the setup)")
    sha = kernels.source_sha()
    assert ctypes.c_char_p.in_dll(lib, "parjam_src_sha").value.decode() == sha
    target = tmp_path / "k.so"
    assert kernels.compile_library(str(target)) is None
    built = ctypes.CDLL(str(target))
    assert ctypes.c_char_p.in_dll(built, "parjam_src_sha").value.decode() == sha
    assert kernels.compile_library(str(tmp_path / "x.so"), cc="/nonexistent/cc") is not None


def test_fused_step_after_a_forced_rebuild(world):
    """A rebuild between fused steps (new slab bounds, migration, ghosts, pairs): the next
    step's forces are those of a fresh evaluation, bitwise."""
    pack = random_packing(3, 200, 0.7, 2.0, "bi", 1.4, np.random.default_rng(12))
    ff = ForceField(world, pack.diam, pack.L, 3, 2.0)
    ff.set_positions(pack.pos)
    g = ff.vec()
    eng = ff.start_engine()
    s = eng.start()
    s = eng.step(0.05, False, 0.9, 0.0, s)
    before = eng.n_rebuilds
    eng.rebuild(rebalance=True)
    s = eng.step(0.05, False, 0.9, 0.0, s)
    assert eng.n_rebuilds == before + 1
    ff.sync_engine()  # the engine's positions into ff.x
    e = ff.evaluate(g)
    assert np.array_equal(gather_engine(ff, eng.f), gather(ff, g))
    assert s.energy == pytest.approx(e, rel=1e-14)
    ff.stop_engine()
    g.destroy()
    ff.destroy()


@pytest.mark.parametrize("move, rebuilt", [(0.1, False), (0.7, True)])
def test_one_particle_moving_past_half_the_skin_rebuilds_everywhere(world, move, rebuilt):
    """Only particle 0 moves, by 0.1 or 0.7 skins in one fused step: the list is rebuilt on
    every rank exactly when the move passes half the skin (one rank: the kernel's own check;
    several: the bound from the last reduction, which no other rank's particles raise), and
    the forces equal a fresh evaluation bitwise either way."""
    pack = random_packing(3, 300, 0.6, 2.0, "mono", 1.4, np.random.default_rng(4))
    ff = ForceField(world, pack.diam, pack.L, 3, 2.0)
    ff.set_positions(pack.pos)
    g = ff.vec()
    dt = 0.01
    v = np.zeros((ff.hi - ff.lo, 3))
    if ff.lo == 0:
        v[0] = np.array([1.0, 0.0, 0.0]) * move * ff.skin / dt
    eng = ff.start_engine(v)
    s = eng.start()
    before = eng.n_rebuilds
    x0 = np.array(gather(ff))
    # no force term (f zeroed, the ghosts' copies too, mix_f = 0): v' = v, x' = x + dt v
    eng.f_all[:] = 0.0
    s = eng.step(dt, False, 1.0, 0.0, s)
    x1 = np.array(gather(ff))
    assert np.abs(x1[0] - x0[0] - [move * ff.skin, 0, 0]).max() < 1e-12
    assert np.array_equal(x1[1:], x0[1:])
    assert (eng.n_rebuilds == before + 1) == rebuilt
    e = ff.evaluate(g)
    assert np.array_equal(gather_engine(ff, eng.f), gather(ff, g))
    assert s.energy == pytest.approx(e, rel=1e-14)
    ff.stop_engine()
    g.destroy()
    ff.destroy()
