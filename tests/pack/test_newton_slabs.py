"""Newton's Verlet list, Hessian and steps without a gather (parjam.pack.forces.ForceField.slab_pairs):
on several ranks the pairs found on the slabs are exactly the serial cell search's,
the assembled Hessian is the serial one, and damped Newton steps from a perturbed jammed state
end where the serial ones end, to round-off; 2 ranks in the MPI pass, 3 through one serial
test."""

import os

import numpy as np
import pytest
from mpi4py import MPI

from parjam import env
from parjam.pack import cellsearch, minimize
from parjam.pack.forces import ForceField
from parjam.files.h5md import read_packing
from parjam.net.system import wrap

from conftest import DATA, run_on_ranks

COMM = MPI.COMM_WORLD
PETSc = env.petsc()
NAMES = ["ref_d3_mono_N128_dphi1e-03.h5", "ref_d2_bi_N128_dphi1e-03.h5"]


def perturbed(name, scale=1e-4):
    pack = read_packing(os.path.join(DATA, name))
    rng = np.random.default_rng(11)
    pack.pos = wrap(pack.pos + scale * rng.standard_normal(pack.pos.shape), pack.L)
    return pack


def field(comm, pack):
    ff = ForceField(comm, pack.diam, pack.L, pack.d, pack.alpha, pack.eps)
    ff.set_positions(pack.pos)
    return ff


@pytest.mark.parametrize("name", NAMES)
def test_slab_pairs_are_the_cell_search(name):
    pack = perturbed(name)
    ff = field(PETSc.COMM_WORLD, pack)
    try:
        cut = ff.dmax + ff.skin
        got = ff.slab_pairs(cut)
        want = cellsearch.cell_pairs(wrap(pack.pos, pack.L), pack.L, cut, ff.lo, ff.hi)
        if want is None:  # no compiled library: the k-d tree's pairs
            from parjam.net.system import neighbour_pairs_touching
            want = neighbour_pairs_touching(pack.pos, pack.L, cut, ff.lo, ff.hi)
        assert np.array_equal(got, want)
    finally:
        ff.destroy()


@pytest.mark.parametrize("name", NAMES)
def test_hessian_and_newton_steps_equal_the_serial_ones(name):
    pack = perturbed(name, 1e-7)  # inside the minimum's basin: Newton converges in 2-3 steps
    ref = field(PETSc.COMM_SELF, pack)
    ff = field(PETSc.COMM_WORLD, pack)
    try:
        H0, H = ref.hessian(shift=1e-3), ff.hessian(shift=1e-3)
        lo, hi = H.getOwnershipRange()
        cols = range(pack.n * pack.d)
        assert np.allclose(H.getValues(range(lo, hi), cols), H0.getValues(range(lo, hi), cols),
                           rtol=0.0, atol=1e-14)
        r0 = minimize.newton(ref, 1e-13, max_steps=4)
        r1 = minimize.newton(ff, 1e-13, max_steps=4)
        assert r0.status == "converged" and r0.newton_steps >= 2 and r0.fmax <= 1e-13
        assert r1.newton_steps == r0.newton_steps and r1.status == r0.status
        assert r1.energy == pytest.approx(r0.energy, rel=1e-9, abs=1e-25)
        x0 = ref.local(ref.x)[ff.lo:ff.hi]
        dx = ff.local(ff.x) - x0
        dx -= pack.L * np.rint(dx / pack.L)
        assert np.abs(dx).max() < 1e-10
    finally:
        ref.destroy()
        ff.destroy()


@pytest.mark.serial
def test_the_same_on_three_ranks():
    res = run_on_ranks("test_newton_slabs.py", 3)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
