"""Elastic moduli by linear response (parjam.vib.moduli): against a dense pseudo-inverse,
against finite strains of the periodic box followed by re-minimisation, 1 rank vs 2 ranks,
the dphi scalings and bad input.  Runs serially and under ``mpirun -n 2``."""

import os
import subprocess
import sys

import numpy as np
import pytest

from parjam.net.blocks import contact_blocks
from parjam import env
from parjam.net import potential
from parjam.vib import hessian, moduli
from parjam.errors import ParjamError
from parjam.study.fits import fit_power
from parjam.net.network import analyze
from parjam.pack.packing import make_jammed
from parjam.net.system import neighbour_pairs, pair_geometry
from conftest import ROOT

SELF = env.petsc().COMM_SELF


@pytest.fixture(scope="session")
def packs():
    """2D (bidisperse) and 3D (mono) N = 64 packings at dphi = 1e-2 (same on every rank)."""
    return {d: make_jammed(d, 64, [1e-2], seed=1, comm=SELF)[1][0] for d in (2, 3)}


@pytest.fixture(scope="session")
def results(packs, world):
    return {d: moduli.compute(p, comm=world) for d, p in packs.items()}


# --- an independent finite-strain reference -------------------------------------------------
class StrainedBox:
    """The non-rattlers of a packing in the affinely deformed periodic box x -> F x + u: energy,
    forces, Cauchy stress, and a dense Newton re-minimisation over u at fixed F."""

    def __init__(self, pack, skin=0.1):
        act = ~analyze(pack).rattler
        pos, diam = pack.pos[act], pack.diam[act]
        pairs = neighbour_pairs(pos, pack.L, diam.max() * (1 + skin))
        self.r0, _, self.sigma = pair_geometry(pos, pack.L, diam, pairs)
        self.i, self.j = pairs[:, 0], pairs[:, 1]
        self.n, self.d = len(pos), pack.d
        self.alpha, self.eps, self.V0 = pack.alpha, pack.eps, pack.volume

    def geometry(self, F, u):
        w = self.r0 @ F.T + u[self.j] - u[self.i]
        return w, np.sqrt((w * w).sum(axis=1))

    def energy_gradient(self, F, u):
        w, r = self.geometry(F, u)
        e = potential.energy(r, self.sigma, self.alpha, self.eps).sum()
        f = (potential.dV(r, self.sigma, self.alpha, self.eps) / r)[:, None] * w
        g = np.zeros((self.n, self.d))
        for a in range(self.d):
            g[:, a] = (np.bincount(self.j, f[:, a], self.n) - np.bincount(self.i, f[:, a], self.n))
        return e, g

    def relax(self, F, tol=1e-15, steps=30):
        u = np.zeros((self.n, self.d))
        T = np.kron(np.ones((self.n, 1)), np.eye(self.d)) / np.sqrt(self.n)
        for _ in range(steps):
            e, g = self.energy_gradient(F, u)
            if np.abs(g).max() < tol:
                break
            w, r = self.geometry(F, u)
            c = r < self.sigma
            K = contact_blocks(w[c], r[c], self.sigma[c], self.alpha, self.eps)
            H = hessian.dense_hessian(self.n, self.d, self.i[c], self.j[c], K)
            u += np.linalg.solve(H + T @ T.T, -g.ravel()).reshape(self.n, self.d)
        e, g = self.energy_gradient(F, u)
        assert np.abs(g).max() < 1e-13
        return e, u

    def stress(self, F, u):
        w, r = self.geometry(F, u)
        t = potential.dV(r, self.sigma, self.alpha, self.eps) / r
        return np.einsum("k,ka,kb->ab", t, w, w) / (self.V0 * np.linalg.det(F))

    def energy_curvature(self, E, g=1e-5):
        """(1/V) d^2 U / d gamma^2 of the relaxed energy under F = I + gamma E."""
        I = np.eye(self.d)
        e = [self.relax(I + s * g * E)[0] for s in (1.0, -1.0, 0.0)]
        return (e[0] + e[1] - 2.0 * e[2]) / g**2 / self.V0

    def stress_slope(self, E, g=1e-6):
        """d(Cauchy stress)/d gamma of the relaxed state under F = I + gamma E."""
        out = []
        for s in (1.0, -1.0):
            F = np.eye(self.d) + s * g * E
            out.append(self.stress(F, self.relax(F)[1]))
        return (out[0] - out[1]) / (2.0 * g)


def strains(d):
    """Compression, a volume-preserving diagonal stretch, and a symmetric xy shear."""
    shear = np.zeros((d, d))
    shear[0, 1] = shear[1, 0] = 1.0
    return {"compression": np.eye(d), "stretch": np.diag([1.0, -1.0] + [0.0] * (d - 2)),
            "shear": shear}


# --- tests ----------------------------------------------------------------------------------
@pytest.mark.parametrize("d", [2, 3])
def test_dense_pseudo_inverse(packs, results, d):
    """C^U = C_aff - (1/V) Xi^T D^+ Xi with numpy's pinv of the dense Hessian."""
    an = moduli.active_network(packs[d], SELF)  # every half-edge on this rank
    once = an.pi < an.pj
    H = hessian.dense_hessian(an.n, an.d, an.pi[once], an.pj[once], an.blocks[once])
    X = np.array([x.ravel() for x in moduli.strain_force_fields(0, an.n, an.pi, an.pj, an.rij,
                                                                 an.blocks)])
    np.testing.assert_allclose(X.reshape(len(X), an.n, d).sum(axis=1), 0.0, atol=1e-14)
    ref = moduli.energy_tensor(results[d].c_affine, X @ np.linalg.pinv(H) @ X.T, d,
                               packs[d].volume)
    scale = np.abs(ref).max()
    assert np.abs(results[d].c_energy - ref).max() < 1e-10 * scale


@pytest.mark.parametrize("d", [2, 3])
def test_finite_strain_energy(packs, results, d):
    """E:C^U:E equals the curvature of the re-minimised energy under finite strains (1e-4)."""
    box = StrainedBox(packs[d])
    scale = abs(np.einsum("aabb->", results[d].c_energy)) / d**2  # bulk-like scale
    for name, E in strains(d).items():
        lr = np.einsum("ab,abcd,cd->", E, results[d].c_energy, E)
        fd = box.energy_curvature(E)
        assert abs(fd - lr) < 1e-4 * max(abs(lr), 0.1 * scale), (name, fd, lr)
    # the non-affine relaxation matters: the affine (Born) term alone is far off in shear
    E = strains(d)["shear"]
    born = np.einsum("ab,abcd,cd->", E, results[d].c_affine, E)
    assert abs(born - box.energy_curvature(E)) > 0.1 * abs(born)


@pytest.mark.parametrize("d", [2, 3])
def test_finite_strain_stress(packs, results, d):
    """The stress-strain tensor B_ijkl gives the Cauchy stress change of the re-minimised state
    (checks the pre-stress terms of C and B as well)."""
    box = StrainedBox(packs[d])
    Bt = results[d].stiffness
    for name, E in strains(d).items():
        lr = np.einsum("abcd,cd->ab", Bt, E)
        fd = box.stress_slope(E)
        assert np.abs(fd - lr).max() < 1e-4 * np.abs(lr).max(), (name, fd, lr)
    # bulk modulus = -V dp/dV under isotropic compression (V = V0 (1 + g)^d)
    dp = -np.trace(box.stress_slope(np.eye(d))) / d
    assert abs(-dp / d - results[d].bulk) < 1e-4 * results[d].bulk


def test_softest_shear_direction(packs, results):
    """G_min and its strain: the stress response along it agrees with finite strain (so a
    packing unstable to some shear in its fixed box, G_min < 0, is detected, as the 2D packing
    here is at the time of writing), and no other deviatoric strain is softer."""
    for d, mod in results.items():
        gmin, E = moduli.softest_shear(mod.stiffness)
        assert gmin == pytest.approx(mod.shear_min)
        assert np.trace(E) == pytest.approx(0.0, abs=1e-12)
        assert np.sum(E * E) == pytest.approx(1.0)
        box = StrainedBox(packs[d])
        fd = np.sum(E * box.stress_slope(E))
        assert abs(fd - 2.0 * gmin) < 1e-4 * mod.bulk
        assert mod.shear_min <= mod.shear
        for name in ("stretch", "shear"):
            trial = strains(d)[name]
            dev = trial - np.trace(trial) / d * np.eye(d)
            dev /= np.sqrt(np.sum(dev * dev))
            assert np.einsum("ab,abcd,cd->", dev, mod.stiffness, dev) >= 2.0 * gmin - 1e-12


@pytest.mark.parametrize("d", [2, 3])
def test_one_vs_all_ranks_and_convergence(packs, results, world, d):
    """COMM_SELF and COMM_WORLD give the same tensors; every KSP solve reached its tolerance."""
    one = moduli.compute(packs[d], comm=SELF)
    many = results[d]
    assert np.abs(one.stiffness - many.stiffness).max() < 1e-10 * np.abs(one.stiffness).max()
    for mod in (one, many):
        assert mod.solver["ksp_type"] == "cg"
        assert len(mod.solver["residuals"]) == d * (d + 1) // 2
        assert mod.solver["max_residual"] < mod.solver["rtol"]
        # a factorisation (one rank) converges at once; block Jacobi (several) takes more
        cap = 50 if mod.solver["pc_type"] == "cholesky" else 1000
        assert all(0 < it < cap for it in mod.solver["iterations"])
    assert one.solver["pc_type"] == "cholesky"
    assert many.solver["pc_type"] == ("asm" if world.getSize() > 1 else "cholesky")


@pytest.mark.parametrize("d", [2, 3])
def test_block_jacobi_preconditioner(packs, world, d):
    """The preconditioner of several ranks (block Jacobi, one ICC(0) block per rank),
    forced on every communicator (one block on one rank): the same tensors as the factorisation
    on one rank, whose agreement with the dense pseudo-inverse is tested above."""
    ref = moduli.compute(packs[d], comm=SELF)
    bj = moduli.compute(packs[d], comm=world, distributed=True)
    assert bj.solver["pc_type"] == "asm"
    assert bj.solver["max_residual"] < bj.solver["rtol"]
    assert np.abs(bj.stiffness - ref.stiffness).max() < 1e-9 * np.abs(ref.stiffness).max()
    assert bj.bulk == pytest.approx(ref.bulk, rel=1e-9)
    assert bj.shear == pytest.approx(ref.shear, rel=1e-8)


def test_scaling_exponents():
    """3D N = 128, 4 members, alpha = 2: B ~ dphi^0 and G ~ dphi^(1/2) (generous bounds).

    At dphi = 1e-4 (N^2 dphi ~ 1.6) the finite-size shear modulus is ~ 0 on average, so the G fit
    uses dphi >= 1e-3; B uses the whole ladder."""
    dphis = [1e-4, 1e-3, 1e-2, 1e-1]
    B, G = [], []
    for member in range(4):
        _, ladder = make_jammed(3, 128, dphis, seed=0, member=member, comm=SELF)
        mods = [moduli.compute(p, comm=env.petsc().COMM_WORLD) for p in ladder]
        B.append([m.bulk for m in mods])
        G.append([m.shear for m in mods])
    fB, fG = fit_power(dphis, B), fit_power(dphis[1:], np.array(G)[:, 1:])
    (sB, eB), (sG, eG) = ((f["exponent"], f["exponent_err"]) for f in (fB, fG))
    assert -0.05 < sB < 0.25, (sB, eB)
    assert 0.3 < sG < 0.7, (sG, eG)
    assert 0.0 < eG < 0.2 and 0.0 < eB < 0.1
    ratio = np.array(G)[:, 1:].mean(axis=0) / np.array(B)[:, 1:].mean(axis=0)
    assert 0.25 < np.polyfit(np.log(dphis[1:]), np.log(ratio), 1)[0] < 0.7


def test_unjammed_packing_is_rejected(packs, world):
    loose = packs[3].rescaled(packs[3].phi - 0.05)
    with pytest.raises(ParjamError, match="not jammed"):
        moduli.compute(loose, comm=world)


def test_extra_zero_modes_are_rejected(packs, world):
    """A dynamical matrix with a free particle (zero modes beyond the translations): the
    response to a force on it does not exist, and the solve reports it instead of a number."""
    an = moduli.active_network(packs[3], world)
    blocks = an.blocks.copy()
    blocks[(an.pi == 0) | (an.pj == 0)] = 0.0
    D = hessian.assemble(world, an.n, 3, an.pi, an.pj, blocks, rows=an.rows)
    rhs = moduli.strain_force_fields(*an.rows, an.pi, an.pj, an.rij, an.blocks)
    try:
        with pytest.raises(ParjamError, match="zero modes beyond"):
            moduli.solve_responses(world, D, rhs, 3)
    finally:
        D.destroy()


@pytest.mark.serial
def test_cli(packs, tmp_path):
    """``parjam moduli`` on 1 and 2 ranks: the printed summary, /moduli/* in the output file,
    and a one-line error with a non-zero exit for an unjammed packing (no file written)."""
    import h5py

    from parjam.files import h5md
    from parjam.net.network import analyze as net_of

    good, bad = tmp_path / "jammed.h5", tmp_path / "loose.h5"
    h5md.write_packing(good, packs[3], net_of(packs[3]), {})
    loose = packs[3].rescaled(packs[3].phi - 0.05)
    h5md.write_packing(bad, loose, net_of(loose), {})
    exe = [sys.executable, "-m", "parjam"]
    root = ROOT
    env_vars = dict(os.environ, PYTHONPATH=root, OMPI_ALLOW_RUN_AS_ROOT="1",
                    OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1", OMP_NUM_THREADS="1")
    ref = moduli.compute(packs[3], comm=SELF)
    for ranks in (1, 2):
        out = tmp_path / f"moduli{ranks}.h5"
        cmd = exe + ["moduli", str(good), "--out", str(out)]
        if ranks == 2:
            cmd = ["mpirun", "--oversubscribe", "-n", "2"] + cmd
        run = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env_vars)
        assert run.returncode == 0, run.stderr
        assert "bulk modulus B" in run.stdout and "max residual" in run.stdout
        with h5py.File(out, "r") as f:
            np.testing.assert_allclose(f["moduli/stiffness"][()], ref.stiffness, rtol=1e-8,
                                       atol=1e-10)
            assert f["moduli"].attrs["G"] == pytest.approx(ref.shear, rel=1e-8)
    run = subprocess.run(exe + ["moduli", str(bad), "--out", str(tmp_path / "no.h5")],
                         capture_output=True, text=True, timeout=300, env=env_vars)
    assert run.returncode != 0
    assert "not jammed" in run.stderr and len(run.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "no.h5").exists()
