"""The potential's derivatives, and the distributed force field against the serial network code."""

import numpy as np
import pytest

from parjam import env
from parjam.net import potential
from parjam.pack.forces import ForceField
from parjam.net.network import analyze, particle_forces
from parjam.pack.packing import random_packing
from parjam.net.system import Packing
from parjam.testing.gather import gather


@pytest.mark.parametrize("alpha", [2.0, 2.5, 3.0])
def test_derivatives_match_finite_differences(alpha):
    sigma = 1.2
    r = np.linspace(0.5, 1.19, 50)
    h = 1e-6
    fd1 = (potential.energy(r + h, sigma, alpha) - potential.energy(r - h, sigma, alpha)) / (2 * h)
    fd2 = (potential.dV(r + h, sigma, alpha) - potential.dV(r - h, sigma, alpha)) / (2 * h)
    np.testing.assert_allclose(potential.dV(r, sigma, alpha), fd1, rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(potential.d2V(r, sigma, alpha), fd2, rtol=1e-6, atol=1e-10)
    assert np.all(potential.energy(np.array([sigma, 1.5]), sigma, alpha) == 0.0)


@pytest.mark.parametrize("d", [2, 3])
def test_distributed_forces_equal_serial_bitwise(world, d):
    """Forces on owned particles do not depend on the number of ranks (fixed summation order)."""
    PETSc = env.petsc()
    pack = random_packing(d, 300, 0.9 if d == 2 else 0.7, 2.0, "bi", 1.4,
                          np.random.default_rng(4))
    results = []
    for comm in (PETSc.COMM_SELF, world):
        ff = ForceField(comm, pack.diam, pack.L, d, pack.alpha)
        ff.set_positions(pack.pos)
        f = ff.vec()
        e = ff.evaluate(f)
        full = gather(ff, f).copy()
        results.append((e, full))
        f.destroy()
        ff.destroy()
    (e1, f1), (e2, f2) = results
    assert np.array_equal(f1, f2)
    assert e2 == pytest.approx(e1, rel=1e-13)
    ref = particle_forces(pack, analyze(pack).all_contacts)
    np.testing.assert_allclose(f1, ref, rtol=0, atol=1e-13 * np.abs(ref).max())
    # Newton's third law: the total force vanishes
    assert np.abs(f1.sum(axis=0)).max() < 1e-12 * np.abs(f1).max()


@pytest.mark.parametrize("d", [2, 3])
def test_halo_forces_follow_moves_between_rebuilds(world, d):
    """Between Verlet rebuilds a force evaluation fetches only the halo of each rank's pairs:
    after moves below half the skin (no rebuild), across the periodic boundary, and past half
    the skin (rebuild), the forces stay bitwise those of one rank and equal the contact sum."""
    PETSc = env.petsc()
    pack = random_packing(d, 400, 0.9 if d == 2 else 0.7, 2.0, "bi", 1.4,
                          np.random.default_rng(11))
    rng = np.random.default_rng(5)
    skin = 0.2 * pack.diam.min()
    moves = [0.2 * skin / np.sqrt(d) * rng.uniform(-1, 1, pack.pos.shape),  # inside skin/2
             np.full(pack.pos.shape, 0.3 * skin / np.sqrt(d)),  # pushes some across x = L
             0.8 * skin * rng.uniform(-1, 1, pack.pos.shape)]  # past skin/2: rebuild
    runs = []
    for comm in (PETSc.COMM_SELF, world):
        ff = ForceField(comm, pack.diam, pack.L, d, pack.alpha)
        pos = pack.pos.copy()
        ff.set_positions(pos)
        f = ff.vec()
        ff.evaluate(f)
        out = []
        for dx in moves:
            pos = pos + dx
            ff.set_positions(pos)  # unwrapped, as during FIRE
            e = ff.evaluate(f)
            out.append((e, gather(ff, f).copy(), ff.n_rebuilds))
        runs.append(out)
        f.destroy()
        ff.destroy()
    assert [r[2] for r in runs[1]] == [1, 1, 2]  # the first two evaluations reuse the list
    for (e1, f1, _), (e2, f2, _), p in zip(runs[0], runs[1], np.cumsum(moves, axis=0)):
        assert np.array_equal(f1, f2)
        assert e2 == pytest.approx(e1, rel=1e-13)
        moved = Packing(np.mod(pack.pos + p, pack.L), pack.diam, pack.L, pack.alpha)
        ref = particle_forces(moved, analyze(moved).all_contacts)
        np.testing.assert_allclose(f1, ref, rtol=0, atol=1e-12 * np.abs(ref).max())


@pytest.mark.parametrize("d", [2, 3])
def test_pairs_touching_a_block_match_the_full_search(d):
    """A rank searches only its block's periodic bounding box grown by the cutoff: the pairs
    touching the block are exactly those of the full search, in the same order, for blocks that
    straddle the periodic boundary, single particles, empty and whole ranges."""
    from parjam.net.system import box_candidates, neighbour_pairs, neighbour_pairs_touching

    n = 2000 if d == 2 else 3000
    pack = random_packing(d, n, 0.9 if d == 2 else 0.7, 2.0, "bi", 1.4, np.random.default_rng(3))
    cut = pack.diam.max() + 0.2 * pack.diam.min()
    # shift the cell-ordered slabs so that some straddle x = L; unwrap some coordinates
    pos = np.mod(pack.pos + 0.37 * pack.L, pack.L)
    unwrapped = pos + pack.L * np.random.default_rng(4).integers(-1, 2, pos.shape)
    full = neighbour_pairs(pos, pack.L, cut)
    i, j = full[:, 0], full[:, 1]
    blocks = [(0, n), (0, 1), (n // 2, n // 2 + 1), (0, n // 8), (n // 3, n // 3 + n // 8),
              (n - n // 8, n), (n // 2, n // 2), (n // 4, 3 * n // 4)]
    for lo, hi in blocks:
        want = full[((i >= lo) & (i < hi)) | ((j >= lo) & (j < hi))]
        got = neighbour_pairs_touching(unwrapped, pack.L, cut, lo, hi)
        assert np.array_equal(got, want), (lo, hi)
    # the point of it: a thin block's search holds a fraction of the particles
    cand = box_candidates(pos, pack.L, cut, n // 3, n // 3 + n // 8)
    assert len(cand) < 0.7 * n


@pytest.mark.parametrize("alpha", [2.0, 2.5])
def test_compiled_kernel_matches_numpy(alpha):
    from parjam.pack import kernels

    if kernels.library() is None:
        pytest.fail("the compiled force kernel did not build (a C compiler is part of the setup)")
    pack = random_packing(3, 400, 0.7, alpha, "poly", 1.3, np.random.default_rng(8))
    from parjam.net.system import neighbour_pairs

    pairs = neighbour_pairs(pack.pos, pack.L, pack.diam.max() * 1.2)
    pi, pj = np.ascontiguousarray(pairs[:, 0]), np.ascontiguousarray(pairs[:, 1])
    out_c, out_n = np.zeros((150, 3)), np.zeros((150, 3))
    e_c = kernels.pair_forces(pi, pj, pack.pos, pack.diam, pack.L, alpha, 1.0, 100, 250, out_c)
    e_n = kernels.pair_forces_numpy(pi, pj, pack.pos, pack.diam, pack.L, alpha, 1.0, 100, 250,
                                     out_n)
    np.testing.assert_allclose(out_c, out_n, rtol=1e-12, atol=1e-15 * np.abs(out_n).max())
    assert e_c == pytest.approx(e_n, rel=1e-12)


@pytest.mark.parametrize("kind", ["full", "relaxed", "stress"])
def test_contact_blocks_in_chunks_are_the_blocks_of_eq1(kind, monkeypatch):
    """blocks.contact_blocks, computed CHUNK contacts at a time, gives each contact's
    V'' n n^T + (V'/r) (I - n n^T) (Eq. 1) to round-off, and the same bits whatever the chunk
    (one pass over all contacts, or passes that split the list anywhere)."""
    from parjam.net import blocks as cb
    rng = np.random.default_rng(5)
    m, d = 3 * cb.CHUNK + 17, 3
    rij = rng.normal(size=(m, d))
    r = np.sqrt((rij * rij).sum(axis=1))
    sigma = r * rng.uniform(1.001, 1.2, m)
    got = cb.contact_blocks(rij, r, sigma, 2.5, 1.3, kind)
    n = rij / r[:, None]
    k = potential.d2V(r, sigma, 2.5, 1.3) if kind != "stress" else np.zeros(m)
    t = potential.dV(r, sigma, 2.5, 1.3) / r if kind != "relaxed" else np.zeros(m)
    for c in (0, 1, cb.CHUNK - 1, cb.CHUNK, m - 1):
        nn = np.outer(n[c], n[c])
        want = k[c] * nn + t[c] * (np.eye(d) - nn)
        np.testing.assert_allclose(got[c], want, rtol=1e-13, atol=1e-13 * abs(want).max())
    for chunk in (m, 1000, 7):
        monkeypatch.setattr(cb, "CHUNK", chunk)
        assert cb.contact_blocks(rij, r, sigma, 2.5, 1.3, kind).tobytes() == got.tobytes()
