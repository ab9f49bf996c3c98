"""The potential's derivatives, and the distributed force field against the serial network code."""

import numpy as np
import pytest

from parjam import env, potential
from parjam.forces import ForceField
from parjam.network import analyze, particle_forces
from parjam.packing import random_packing


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
        full = ff.gather(f).copy()
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


@pytest.mark.parametrize("alpha", [2.0, 2.5])
def test_compiled_kernel_matches_numpy(alpha):
    from parjam import kernels

    if kernels.library() is None:
        pytest.fail("the compiled force kernel did not build (a C compiler is part of the setup)")
    pack = random_packing(3, 400, 0.7, alpha, "poly", 1.3, np.random.default_rng(8))
    from parjam.system import neighbour_pairs

    pairs = neighbour_pairs(pack.pos, pack.L, pack.diam.max() * 1.2)
    pi, pj = np.ascontiguousarray(pairs[:, 0]), np.ascontiguousarray(pairs[:, 1])
    out_c, out_n = np.zeros((150, 3)), np.zeros((150, 3))
    e_c = kernels.pair_forces(pi, pj, pack.pos, pack.diam, pack.L, alpha, 1.0, 100, 250, out_c)
    e_n = kernels._pair_forces_numpy(pi, pj, pack.pos, pack.diam, pack.L, alpha, 1.0, 100, 250,
                                     out_n)
    np.testing.assert_allclose(out_c, out_n, rtol=1e-12, atol=1e-15 * np.abs(out_n).max())
    assert e_c == pytest.approx(e_n, rel=1e-12)
