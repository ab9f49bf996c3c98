"""The same packing on any number of ranks: exact sums (parjam.net.exactsum) equal math.fsum
however the values are split over ranks; the engine's FIRE sums are exact sums of the
per-particle terms; FIRE and Newton (both solvers of parjam.pack.newtonsolve) end in the same
positions, bitwise, on one rank and on all ranks; ``parjam pack`` of one member shared by 1, 2
and 3 ranks writes the same files, bitwise (a quench in 3D, a bisection and ladder in 2D, a
bisection in 2D that escapes saddles).  3
ranks: the serial pass reruns this file under $PARJAM_MPIRUN -n 3.  Resumes on another number
of ranks: tests/pack/test_checkpoint.py."""

import glob
import math
import os
import subprocess
import sys

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from parjam import env
from parjam.files import h5md
from parjam.files.h5md import read_packing
from parjam.net import exactsum
from parjam.net.system import wrap
from parjam.pack import kernels, minimize, newtonsolve
from parjam.pack.engine import SlabEngine
from parjam.pack.fire import FireParams, fire
from parjam.pack.forces import ForceField
from parjam.pack.packing import random_packing
from parjam.testing.gather import gather
from parjam.testing.h5compare import differences

from conftest import DATA, run_on_ranks, subprocess_env

COMM = MPI.COMM_WORLD
PETSc = env.petsc()


def hard_values(rng, n):
    """Values whose naive sums depend on the order: 60 decades of magnitudes, both signs,
    cancelling pairs, subnormals and a few huge terms."""
    v = rng.standard_normal(n) * 10.0 ** rng.integers(-30, 30, n)
    v[: n // 4] = -v[n // 4: 2 * (n // 4)]  # exact cancellations
    v[rng.integers(0, n, 3)] = [1e300, -1e300, 5e-324]
    v[rng.integers(0, n, 3)] = np.ldexp(rng.integers(1, 2**52, 3).astype(float), -1074)
    return rng.permutation(v)


@pytest.mark.parametrize("compiled", [True, False])
def test_exact_sum_is_math_fsum(compiled, monkeypatch):
    """partial + value round the exact sum once, to nearest (ties to even): math.fsum's value,
    for the compiled accumulator and its numpy fallback (the same accumulator, bit for bit)."""
    if not compiled:
        monkeypatch.setattr(exactsum, "compiled", lambda: None)
    elif exactsum.compiled() is None:
        pytest.fail("the compiled kernels are not available (a C compiler is part of the setup)")
    rng = np.random.default_rng(7)
    for n in (1, 2, 7, 300, 5000):
        for _ in range(20):
            v = hard_values(rng, n)
            acc = exactsum.partial(v)
            assert exactsum.value(acc) == math.fsum(v)
            # split anywhere and accumulated in pieces: the same accumulator
            cut = rng.integers(0, n + 1)
            assert np.array_equal(exactsum.partial(v[cut:], exactsum.partial(v[:cut])), acc)
    # ties round to even, specials as IEEE sums them in any order
    assert exactsum.value(exactsum.partial([1.0, 2.0**-53])) == 1.0
    assert exactsum.value(exactsum.partial([1.0, 3 * 2.0**-53])) == 1.0 + 2.0**-51
    assert exactsum.value(exactsum.partial([1.0, 2.0**-53, 2.0**-200])) == 1.0 + 2.0**-52
    assert exactsum.value(exactsum.partial([1e308, 1e308, -1e308])) == 1e308
    assert exactsum.value(exactsum.partial([np.inf, 1.0])) == np.inf
    assert np.isnan(exactsum.value(exactsum.partial([np.inf, -np.inf])))
    assert np.isnan(exactsum.value(exactsum.partial([np.nan, 1.0])))


def block_values(rng):
    """Blocks of values for the compiled accumulator's fast path (parjam/pack/_kernels.c:
    blocks of 256 split on two grids below the block's largest magnitude, the rest value by
    value): each case is one kind of block, several blocks long, with a ragged end."""
    n = 3 * 256 + 37
    x = rng.standard_normal(n)
    tiny = x.copy()
    tiny[rng.integers(0, n, 20)] *= 2.0 ** -60  # bits beyond both grids: the remainder path
    spread = x * 2.0 ** rng.integers(-36, 1, n)  # within the two grids
    grid = np.ldexp(rng.integers(-2**52, 2**52, n).astype(float), rng.integers(-80, -30, n))
    ties = 1.0 + rng.integers(0, 2, n) * 2.0 ** -45 + rng.integers(0, 2, n) * 2.0 ** -44
    cases = {
        "normal": x, "tiny": tiny, "spread": spread, "grid": grid,
        "ties": np.concatenate([ties, -ties[:100]]),
        "cancel": np.concatenate([x, -x[::-1]]),
        "zeros": np.concatenate([np.zeros(300), -np.zeros(300), [2.0 ** -1074]]),
        "subnormal": np.concatenate([x * 2.0 ** -1000, np.ldexp(x, -1060)]),
        "top": x * 2.0 ** 900, "over top": x * 2.0 ** 902,
        "bottom": x * 2.0 ** -899, "below bottom": x * 2.0 ** -902,
        "nan": np.concatenate([x, [np.nan]]), "inf": np.concatenate([x, [np.inf], x]),
        "both inf": np.concatenate([x, [np.inf, -np.inf]]),
        "huge": np.concatenate([x, [8e307, 8e307, -8e307]]),
    }
    return cases


@pytest.mark.parametrize("case", list(block_values(np.random.default_rng(0))))
def test_compiled_blocks_are_the_exact_sum(case):
    """The compiled accumulator (blocks on two grids) and the numpy one (each value split into
    its chunks) hold the same integers for every kind of block, and round to math.fsum (IEEE's
    sum where there are infinities or NaNs), whole or cut anywhere into pieces."""
    if exactsum.compiled() is None:
        pytest.fail("the compiled kernels are not available (a C compiler is part of the setup)")
    rng = np.random.default_rng(5)
    v = block_values(rng)[case]
    for order in (v, rng.permutation(v)):
        acc = exactsum.partial(order)
        cut = rng.integers(0, len(order) + 1)
        assert np.array_equal(exactsum.partial(order[cut:], exactsum.partial(order[:cut])), acc)
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(exactsum, "compiled", lambda: None)
            ref = exactsum.partial(order)
        assert np.array_equal(acc, ref)
        if np.all(np.isfinite(order)):
            assert exactsum.value(acc) == math.fsum(order)
        else:
            assert np.array_equal(exactsum.value(acc), np.sum(order[~np.isfinite(order)]),
                                  equal_nan=True)


def test_sums_over_ranks_are_math_fsum_of_all_values():
    """Each rank holds an uneven slice of the same values: totals over the ranks equal math.fsum
    of all of them (and a naive sum over the ranks would not, for these values)."""
    rng = np.random.default_rng(11)
    v, w = hard_values(rng, 4000), rng.standard_normal(997)
    cuts = np.sort(rng.integers(0, len(v), COMM.size - 1))
    bounds = np.concatenate([[0], cuts, [len(v)]])
    part = v[bounds[COMM.rank]:bounds[COMM.rank + 1]]
    mine = w[COMM.rank::COMM.size]
    got = exactsum.totals(COMM, part, mine)
    assert got == [math.fsum(v), math.fsum(w)]
    assert exactsum.fsum(PETSc.COMM_WORLD, part) == math.fsum(v)
    assert exactsum.totals(COMM) == []


def engine_terms(eng):
    """(exact accumulator of the energy, F.v, |F|^2, |v|^2 per particle) of the engine's own
    particles, by the numpy kernel (the compiled one's reference, same order over pairs and
    components)."""
    acc = np.zeros(exactsum.ACC_LEN, dtype=np.int64)
    f = np.zeros_like(eng.f)
    kernels.pair_forces_numpy(eng.pi, eng.pj, eng.pos, eng.pdiam, eng.L, eng.alpha, eng.eps,
                              0, eng.n_own, f, acc)
    assert np.array_equal(f, eng.f)
    p, f2, v2 = (np.zeros(eng.n_own) for _ in range(3))
    for a in range(eng.d):
        p += eng.f[:, a] * eng.v[:, a]
        f2 += eng.f[:, a] * eng.f[:, a]
        v2 += eng.v[:, a] * eng.v[:, a]
    return acc, p, f2, v2


@pytest.mark.parametrize("d", [2, 3])
def test_fire_sums_are_exact_sums_of_the_particles_terms(d):
    """The engine's sums after some FIRE steps (velocities and forces of both signs) are
    math.fsum of the per-particle terms gathered from all ranks, and the maxima their maxima."""
    pack = random_packing(d, 300, 0.86 if d == 2 else 0.66, 2.0, "bi", 1.4,
                          np.random.default_rng(3))
    mine = np.arange(COMM.rank, pack.n, COMM.size)
    eng = SlabEngine(COMM, pack.L, 2.0, 1.0, 0.2, pack.pos[mine], mine, pack.diam[mine])
    s = eng.start()
    for _ in range(30):
        s = eng.step(0.02, False, 0.9, 0.05, s)
    acc, p, f2, v2 = engine_terms(eng)
    everyone = [np.concatenate(COMM.allgather(a)) for a in (p, f2, v2)]
    assert s.energy == exactsum.value(sum(COMM.allgather(acc))) > 0.0
    for got, terms in zip((s.power, s.f2, s.v2), everyone):
        assert got == math.fsum(terms)
    assert s.fmax == math.sqrt(everyone[1].max()) and s.vmax == math.sqrt(everyone[2].max())
    assert s.power != 0.0


def test_fire_energy_is_the_exact_sum_of_pair_energies():
    """The engine's energy is math.fsum over particles of each particle's pair energies (pairs
    with it as the lower end, summed in partner order), on any number of ranks."""
    pack = random_packing(3, 250, 0.68, 2.0, "mono", 1.4, np.random.default_rng(4))
    mine = np.arange(COMM.rank, pack.n, COMM.size)
    eng = SlabEngine(COMM, pack.L, 2.0, 1.0, 0.2, pack.pos[mine], mine, pack.diam[mine])
    s = eng.start()
    # the serial reference: all pairs in (i, j) order, energies grouped by the lower end
    from parjam.net import potential
    from parjam.net.system import neighbour_pairs, pair_separation

    pairs = neighbour_pairs(pack.pos, pack.L, pack.diam.max())
    rij = pair_separation(pack.pos[pairs[:, 0]], pack.pos[pairs[:, 1]], pack.L)
    r = np.sqrt(rij[:, 0] * rij[:, 0] + rij[:, 1] * rij[:, 1] + rij[:, 2] * rij[:, 2])
    sigma = 0.5 * (pack.diam[pairs[:, 0]] + pack.diam[pairs[:, 1]])
    c = r < sigma
    per = np.bincount(pairs[c, 0], weights=potential.energy(r[c], sigma[c], 2.0, 1.0),
                      minlength=pack.n)
    assert s.energy == math.fsum(per) > 0.0


def _newton_pair(world, pack, steps=4):
    """Newton from ``pack`` on one rank and on all ranks: (MinResult, positions) of each."""
    out = []
    for comm in (PETSc.COMM_SELF, world):
        ff = ForceField(comm, pack.diam, pack.L, pack.d, pack.alpha, pack.eps)
        ff.set_positions(pack.pos)
        res = minimize.newton(ff, 1e-13, max_steps=steps)
        out.append((res, np.array(gather(ff)), ff.newton_ksp.ksp_type))
        ff.destroy()
    return out


@pytest.mark.parametrize("name", ["ref_d3_mono_N128_dphi1e-03.h5", "ref_d2_bi_N128_dphi1e-03.h5"])
@pytest.mark.parametrize("cg", [False, True])
def test_newton_is_bitwise_the_same_on_one_and_all_ranks(world, monkeypatch, name, cg):
    """Damped Newton from a perturbed jammed state: with the factorisation on the first rank
    (RootFactor) and with exact-sum CG (ExactCG, forced by NEWTON_CG_DOF = 0) it reaches the
    tolerance, and the positions and energy on all ranks are the one-rank ones, bitwise."""
    if cg:
        monkeypatch.setattr(newtonsolve, "NEWTON_CG_DOF", 0)
    pack = read_packing(os.path.join(DATA, name))
    rng = np.random.default_rng(11)
    pack.pos = wrap(pack.pos + 1e-7 * rng.standard_normal(pack.pos.shape), pack.L)
    (r1, x1, t1), (rp, xp, tp) = _newton_pair(world, pack, steps=8 if cg else 4)
    assert t1 == tp == ("exact cg" if cg else "preonly")
    assert r1.status == "converged" and r1.fmax <= 1e-13 and r1.newton_steps >= 2
    assert (rp.status, rp.newton_steps) == (r1.status, r1.newton_steps)
    assert rp.energy == r1.energy and rp.fmax == r1.fmax
    assert np.array_equal(xp, x1)


@pytest.mark.parametrize("d, poly", [(2, "bi"), (3, "mono")])
def test_fire_then_newton_is_bitwise_the_same_on_one_and_all_ranks(world, d, poly):
    """minimize (FIRE to a loose tolerance, then Newton) from a random start: the same steps,
    energy and positions, bitwise, on one rank and on all ranks."""
    pack = random_packing(d, 200, 0.88 if d == 2 else 0.70, 2.0, poly, 1.4,
                          np.random.default_rng(9))
    out = []
    for comm in (PETSc.COMM_SELF, world):
        ff = ForceField(comm, pack.diam, pack.L, d, 2.0)
        ff.set_positions(pack.pos)
        res = minimize.minimize(ff, 1e-13)
        out.append((res, np.array(gather(ff))))
        ff.destroy()
    (r1, x1), (rp, xp) = out
    assert r1.ok and r1.fire_steps > 100 and r1.newton_steps > 0
    assert (rp.fire_steps, rp.newton_steps, rp.energy, rp.fmax) == \
        (r1.fire_steps, r1.newton_steps, r1.energy, r1.fmax)
    assert np.array_equal(xp, x1)


PACKS = {
    "quench-3d": ["--dim", "3", "--n", "48", "--phi", "0.70", "--seed", "5"],
    "bisect-ladder-2d": ["--dim", "2", "--n", "32", "--dispersity", "bi", "--dphi", "1e-3",
                         "--seed", "2"],
    # 23 saddle escapes and 2 compression cycles (at phi_c and 1e-8, which stays a flagged
    # saddle): the escape directions and the line energies must be the same bits on every rank
    # count (before, 1 and 2 ranks differed: 23 against 12 escapes)
    "bisect-escapes-2d": ["--dim", "2", "--n", "64", "--dphi", "1e-8", "--seed", "1"],
}


def _pack(out, args, ranks):
    mpirun = os.environ.get("PARJAM_MPIRUN", "mpirun --oversubscribe").split()
    cmd = [sys.executable, "-m", "parjam", "pack", *args, "--out", str(out), "-q"]
    if ranks > 1:
        cmd = mpirun + ["-n", str(ranks)] + cmd
    r = subprocess.run(cmd, env=subprocess_env(), capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr
    return sorted(glob.glob("*.h5", root_dir=out))


@pytest.mark.serial
@pytest.mark.parametrize("case", sorted(PACKS))
def test_pack_shared_by_1_2_3_ranks_writes_the_same_files(tmp_path, case):
    """One member shared by 1, 2 and 3 ranks: every dataset and parameter of every file
    bitwise equal (the ranks sharing it, a provenance entry, and wall times aside)."""
    names = [_pack(tmp_path / f"on{p}", PACKS[case], p) for p in (1, 2, 3)]
    assert names[0] == names[1] == names[2] and names[0]
    if "escapes" in case:  # the case is there for its saddles: they must still be met
        escapes = 0
        for name in names[0]:
            with h5py.File(tmp_path / "on1" / name, "r") as f:
                escapes += int(h5md.observable(f, "escapes"))
        assert escapes >= 4, escapes
    for p in (2, 3):
        for name in names[0]:
            assert differences(tmp_path / "on1" / name, tmp_path / f"on{p}" / name) == [], \
                (p, name)


@pytest.mark.serial
def test_the_same_on_three_ranks():
    """The in-process tests of this file on 3 ranks (a middle rank, uneven slabs)."""
    res = run_on_ranks("test_rank_independence.py", 3, "-k", "not three and not files")
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
