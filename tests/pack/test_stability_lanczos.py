"""The stability check without a factorisation (parjam.vib.lowest, parjam.pack.stability's
``lanczos`` method): its verdicts against the exact inertia (MUMPS LDL^T) and dense LAPACK on
stable packings and on saddles, serially and on 2 ranks (every rank runs every test; the dense
references are computed on each).

Saddles: (1) a stable isostatic packing displaced along its softest mode until a contact opens
(Nc < Nc_iso: floppy modes whose curvature the stress term of Eq. (1) makes negative, of
order -p); (2) a packing's own dynamical matrix with a known eigenvalue moved to -1e-9, -1e-11,
a few s, and inside the round-off band (the operator D - c q q^T, q a dense eigenvector);
(3) a network with one contact left out of its Hessian.
"""

import os
import subprocess
import sys

import numpy as np
import pytest
from mpi4py import MPI

from parjam import env
from parjam.errors import ParjamError
from parjam.net import exactsum, network
from parjam.files.h5md import read_packing
from parjam.pack import jamnet, kernels, stability
from parjam.vib import hessian, lowest, rowproduct
from parjam.testing import saddles

from conftest import DATA, ROOT, run_on_ranks, subprocess_env

COMM = MPI.COMM_WORLD
WORLD = env.petsc().COMM_WORLD
STABLE = ["ref_d3_mono_N128_dphi1e-06.h5", "ref_d3_mono_N128_dphi1e-03.h5",
          "ref_d2_bi_N128_dphi1e-06.h5", "soft_d3_N256_m0.h5"]
LANCZOS = stability.Settings("lanczos", exact_max_dof=0, lanczos=lowest.Settings())
INERTIA = stability.Settings("inertia")


def dense_active(pack):
    """Serial dense D of the non-rattlers (active numbers in particle order), their ids."""
    net = network.analyze(pack)
    c = network.active_contacts(net)
    blocks = hessian.contact_blocks(c.rij, c.r, c.sigma, pack.alpha, pack.eps, "full")
    return (hessian.dense_hessian(net.n_active, pack.d, c.i, c.j, blocks),
            np.flatnonzero(~net.rattler))


def lowest_modes(D, d):
    """Eigenvalues and vectors of D with the d translations moved far above the spectrum."""
    n = D.shape[0] // d
    Dd = D.reshape(n, d, n, d).copy()
    for a in range(d):
        Dd[:, a, :, a] += 1e3 / n
    return np.linalg.eigh(Dd.reshape(n * d, -1))


def dense_count(pack, s):
    D, _ = dense_active(pack)
    lam, _ = lowest_modes(D, pack.d)
    return int(np.sum(lam < -s))


@pytest.mark.parametrize("name", STABLE)
def test_stable_packings_agree_with_the_exact_inertia(name):
    """Stable packings: the Lanczos test says 'no eigenvalue below -s' with a failure bound
    below delta, as the MUMPS inertia and LAPACK do, and its lowest Ritz value is the dense
    lowest non-translational eigenvalue."""
    pack = read_packing(os.path.join(DATA, name))
    net = jamnet.from_packing(COMM, pack)
    new = stability.check(WORLD, net, LANCZOS)
    old = stability.check(WORLD, net, INERTIA)
    assert old.n_negative == dense_count(pack, old.shift) == 0
    assert new.method == "lanczos" and new.n_negative == 0 and new.stable == old.stable
    assert 0.0 < new.failure <= LANCZOS.lanczos.delta
    lam, _ = lowest_modes(dense_active(pack)[0], pack.d)
    assert new.lowest == pytest.approx(lam[0], rel=1e-6, abs=1e-3 * new.shift)


def test_saddle_along_the_soft_mode_is_found_with_its_direction():
    """Nc < Nc_iso after contacts opened along the soft mode: Lanczos finds it unstable as MUMPS
    and LAPACK do (counting at least one of their negative eigenvalues), its witness's quotient
    lies between the lowest eigenvalue and -2 s, and the escape direction is the dense lowest
    eigenvector, its eigenvalue to 1e-6."""
    pack = saddles.along_soft_mode(read_packing(os.path.join(DATA, STABLE[0])))
    net = jamnet.from_packing(COMM, pack)
    assert net.excess < 0
    new = stability.check(WORLD, net, LANCZOS)
    old = stability.check(WORLD, net, INERTIA)
    want = dense_count(pack, old.shift)
    assert want >= 1 and old.n_negative == want
    assert new.method == "lanczos" and not new.stable
    assert 1 <= new.n_negative <= want  # the Lanczos count: those found by its verdict
    D, active = dense_active(pack)
    lam, vec = lowest_modes(D, pack.d)
    assert lam[0] < -1e-9
    # the witness: not below the lowest eigenvalue but for the round-off of the product and of
    # LAPACK's value, a few eps ||D|| each (0.01 s = 1 eps ||D||; 1.9 seen): 10 eps ||D||
    assert lam[0] - 0.1 * new.shift <= new.lowest <= -2.0 * new.shift
    direction, got = stability.softest_direction(WORLD, net, new)
    assert got == pytest.approx(lam[0], rel=1e-6)
    full = np.zeros((pack.n, pack.d))
    for ids, rows in COMM.allgather((net.state.ids, direction)):
        full[ids] = rows
    ref = np.zeros((pack.n, pack.d))
    ref[active] = vec[:, 0].reshape(-1, pack.d)
    ref /= np.sqrt(np.einsum("ij,ij->i", ref, ref)).max()
    assert np.abs(np.sign(np.vdot(full, ref)) * full - ref).max() < 1e-4


class RankOne:
    """The operator D - c q q^T (q a unit vector off the translations): D's spectrum with one
    eigenvalue moved by -c."""

    def __init__(self, D, q, c):
        self.D, self.q, self.c = D, q, c
        self.mpi, self.n = D.mpi, D.n

    def apply(self, v):
        return self.D.apply(v) - self.c * exactsum.fsum(self.mpi, self.q * v) * self.q


def shell(H, q, c):
    D = H.product(WORLD)
    return RankOne(D, q, c), D


@pytest.mark.parametrize("target, verdict", [
    (-1e-9, lowest.BELOW), (-1e-11, lowest.BELOW), (-3.0, lowest.BELOW),
    (-1.5, lowest.INCONCLUSIVE), (-0.5, lowest.NOT_BELOW), (1e-9, lowest.NOT_BELOW)])
def test_known_lowest_eigenvalue_is_resolved(target, verdict):
    """D of a stable packing with its lowest eigenpair moved to ``target`` (absolute below
    -1e-10, in units of s above): -1e-9 and -1e-11 (10^-10 and 10^-12 of ||D||) and -3 s are
    found below -s, with the eigenvalue to 1e-6; -0.5 s and +1e-9 are not; -1.5 s lies in the
    round-off band [-2 s, 0] and is reported inconclusive (the exact inertia then decides)."""
    pack = read_packing(os.path.join(DATA, STABLE[0]))
    net = jamnet.from_packing(COMM, pack)
    H = stability.active_hessian(net)
    s = stability.shift_for(H.norm)
    lam, vec = lowest_modes(dense_active(pack)[0], pack.d)
    want = target if abs(target) < 1e-6 else target * s
    q = rows_of_active(net, vec[:, 0])
    A, D = shell(H, q, lam[0] - want)
    start = lowest.start_rows(H.edges.ids, H.d, 1)
    try:
        res = lowest.lowest_test(A, H.d, s, start)
        if verdict == lowest.BELOW:
            converged = lowest.lowest_test(A, H.d, s, start, want_vector=True)
    finally:
        D.destroy()
    assert res.verdict == verdict, res
    if verdict == lowest.BELOW:
        assert res.n_below == 1
        assert want - 0.01 * s <= res.lowest <= -2.0 * s  # the witness: Courant-Fischer
        assert converged.verdict == lowest.BELOW
        assert converged.lowest == pytest.approx(want, rel=1e-6)
        assert converged.residual <= max(1e-5 * abs(want), 0.02 * s)
    if verdict == lowest.NOT_BELOW:
        assert res.failure <= lowest.DELTA


def rows_of_active(net, field):
    """This rank's rows [lo, hi) of an active-order (serial) vector of d components each."""
    ids = net.active.ids
    serial = np.sort(np.concatenate(COMM.allgather(ids)))
    return field.reshape(-1, net.d)[np.searchsorted(serial, ids)].ravel()


def test_hessian_without_two_contacts():
    """The Hessian of an isostatic network with two contacts left out (each between particles
    with more than d + 1 contacts: Nc = Nc_iso - 2 leaves a floppy mode, made negative by the
    stress term; one contact fewer only frees the box's degree of freedom): Lanczos finds it
    below -s as LAPACK does."""
    pack = read_packing(os.path.join(DATA, STABLE[0]))
    ref = network.analyze(pack)
    c = network.active_contacts(ref)
    deg = np.bincount(c.i, minlength=ref.n_active) + np.bincount(c.j, minlength=ref.n_active)
    free = np.flatnonzero((deg[c.i] > pack.d + 1) & (deg[c.j] > pack.d + 1))
    first = [free[0], next(k for k in free if not {c.i[k], c.j[k]} & {c.i[free[0]],
                                                                        c.j[free[0]]})]
    blocks = hessian.contact_blocks(c.rij, c.r, c.sigma, pack.alpha, pack.eps, "full")
    keep = ~np.isin(np.arange(len(c.r)), first)
    lam, _ = lowest_modes(hessian.dense_hessian(ref.n_active, pack.d, c.i[keep], c.j[keep],
                                                blocks[keep]), pack.d)
    active = np.flatnonzero(~ref.rattler)
    gone = [(int(active[c.i[k]]), int(active[c.j[k]])) for k in first]  # particle ids
    net = jamnet.from_packing(COMM, pack)
    H = stability.active_hessian(net)
    e = H.edges
    ids = np.concatenate(COMM.allgather(e.ids))  # active number -> particle id
    pi, pj = ids[e.i], ids[e.j]
    drop = np.zeros(len(pi), dtype=bool)
    for a, b in gone:
        drop |= ((pi == a) & (pj == b)) | ((pi == b) & (pj == a))
    assert COMM.allreduce(int(drop.sum())) == 4  # the two contacts' half-edges
    A = rowproduct.HalfEdgeProduct(WORLD, e.n, H.d, e.lo, e.hi, e.i[~drop], e.j[~drop],
                                   H.blocks[~drop])
    s = stability.shift_for(H.norm)
    try:
        res = lowest.lowest_test(A, H.d, s, lowest.start_rows(e.ids, H.d, 7))
    finally:
        A.destroy()
    assert lam[0] < -1e-9 and lam[1] > 0.0
    assert res.verdict == lowest.BELOW and res.n_below == 1
    # a Ritz value is not below the lowest eigenvalue but for round-off, which is a few
    # eps ||D|| (0.01 s = 1 eps ||D||; here 1.3 eps ||D|| was seen, with OpenBLAS's generic
    # kernels): 10 eps ||D||, still 10^5 below |lam[0]|
    assert lam[0] - 0.1 * s <= res.lowest <= -2.0 * s


def test_inconclusive_falls_back_to_the_exact_inertia_or_is_undecided():
    """A step budget too small to decide: below EXACT_MAX_DOF rows the exact inertia decides
    (and says why), above it the state is undecided: not stable, not escaped from."""
    pack = read_packing(os.path.join(DATA, STABLE[0]))
    net = jamnet.from_packing(COMM, pack)
    short = lowest.Settings(max_steps=20)
    cur = stability.check(WORLD, net, stability.Settings("lanczos", 10**6, short))
    assert cur.method == "inertia" and cur.stable and "budget" in cur.why
    cur = stability.check(WORLD, net, stability.Settings("lanczos", 0, short))
    assert cur.method == "undecided" and cur.n_negative == -1
    assert not cur.stable and not cur.decided


def test_start_vector_does_not_depend_on_the_distribution():
    ids = np.arange(50, dtype=np.int64)
    whole = lowest.start_rows(ids, 3, 11)
    parts = np.concatenate([lowest.start_rows(ids[:17], 3, 11),
                            lowest.start_rows(ids[17:], 3, 11)])
    assert np.array_equal(whole, parts)
    assert abs(whole.mean()) < 0.3 and 0.7 < whole.std() < 1.3
    assert not np.array_equal(whole, lowest.start_rows(ids, 3, 12))


def test_options_choose_the_method():
    PETSc = env.petsc()
    opts = PETSc.Options()
    try:
        opts["stability_method"] = "inertia"
        opts["stability_lanczos_max_it"] = 123
        cfg = stability.Settings.from_options()
        assert cfg.method == "inertia" and cfg.lanczos.max_steps == 123
        opts["stability_method"] = "cholesky"
        with pytest.raises(ParjamError, match="stability_method"):
            stability.Settings.from_options()
        opts["stability_method"] = "lanczos"
        for key, bad in (("delta", 0), ("delta", 1.5), ("max_it", 0), ("rtol", 2),
                         ("check_every", 0)):
            opts[f"stability_lanczos_{key}"] = bad
            with pytest.raises(ParjamError, match=f"stability_lanczos_{key}"):
                stability.Settings.from_options()
            opts.delValue(f"stability_lanczos_{key}")
    finally:
        for k in ("stability_method", "stability_lanczos_max_it"):
            opts.delValue(k)
    assert stability.Settings.from_options().method == "auto"


def test_auto_takes_the_exact_inertia_up_to_its_size():
    """-stability_method auto (the default): the exact inertia for matrices of at most
    -stability_auto_max_dof rows, the Lanczos test above; both give the same verdict."""
    cfg = stability.Settings()
    assert cfg.method == "auto"
    assert cfg.method_for(stability.AUTO_MAX_DOF) == "inertia"
    assert cfg.method_for(stability.AUTO_MAX_DOF + 1) == "lanczos"
    assert stability.Settings("lanczos").method_for(10) == "lanczos"
    assert stability.Settings("inertia").method_for(10**9) == "inertia"
    PETSc = env.petsc()
    opts = PETSc.Options()
    try:
        opts["stability_auto_max_dof"] = -1
        with pytest.raises(ParjamError, match="stability_auto_max_dof"):
            stability.Settings.from_options()
        opts["stability_auto_max_dof"] = 77
        assert stability.Settings.from_options().auto_max_dof == 77
    finally:
        opts.delValue("stability_auto_max_dof")
    net = jamnet.from_packing(WORLD, read_packing(os.path.join(DATA, "soft_d3_N256_m0.h5")))
    small = stability.check(WORLD, net, stability.Settings("auto", lanczos=lowest.Settings()))
    large = stability.check(WORLD, net, stability.Settings("auto", 0, lowest.Settings(), 0))
    assert small.method == "inertia" and large.method == "lanczos"
    assert small.stable == large.stable and small.n_negative == large.n_negative


@pytest.mark.serial
@pytest.mark.parametrize("option", [["-stability_method", "cholesky"],
                                    ["-stability_lanczos_delta", "2"]])
def test_pack_refuses_bad_stability_options_before_any_work(tmp_path, option):
    out = tmp_path / "out"
    res = subprocess.run([sys.executable, "-m", "parjam", "pack", "--n", "32", "--phi", "0.7",
                          "--out", str(out), "-q", *option], cwd=ROOT, env=subprocess_env(),
                         capture_output=True, text=True, timeout=300)
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1, res.stderr
    assert lines[0].startswith("parjam: error: " + option[0])
    assert not out.exists()


# --- the same bits on any number of ranks --------------------------------------------------
# Every test below runs the check on all ranks (COMM_WORLD) and on this rank alone (COMM_SELF,
# the one-rank run) and asserts that the two agree bit for bit; the serial pass reruns them on
# 3 ranks.


def on_self_and_all(pack):
    """The packing's JamNetwork on all ranks and on this rank alone, with their PETSc comms."""
    PETSc = env.petsc()
    return [(jamnet.from_packing(comm, pack), pcomm)
            for comm, pcomm in ((COMM, WORLD), (MPI.COMM_SELF, PETSc.COMM_SELF))]


def by_id(net, rows):
    """Owned rows of ``net.state`` (one per particle) as a whole (N, d) array, on every rank."""
    full = np.zeros((net.n, net.d))
    for ids, part in net.state.comm.allgather((net.state.ids, rows)):
        full[ids] = part
    return full


@pytest.mark.parametrize("name", [STABLE[0], STABLE[2]])
def test_product_is_the_dense_one_and_the_same_bits_on_any_number_of_ranks(name):
    """HalfEdgeProduct: D v equals the dense D v to round-off, and on all ranks it is the
    one-rank product bit for bit (as are ||D|| and the shift s); PETSc's MatMult of the same
    rows is not (its rows are summed as the owned columns and then the others)."""
    pack = read_packing(os.path.join(DATA, name))
    got = []
    for net, pcomm in on_self_and_all(pack):
        H = stability.active_hessian(net)
        op = H.product(pcomm)
        try:
            v = lowest.start_rows(H.edges.ids, H.d, 3).ravel()
            w = op.apply(v).reshape(-1, H.d)
        finally:
            op.destroy()
        ids = np.concatenate(net.state.comm.allgather(H.edges.ids))
        rows = np.concatenate(net.state.comm.allgather(w))
        got.append((H.norm, stability.shift_for(H.norm), rows[np.argsort(ids)]))
    (n_all, s_all, w_all), (n_one, s_one, w_one) = got
    assert n_all == n_one and s_all == s_one
    assert np.array_equal(w_all, w_one)
    # the compiled kernel and the numpy fallback: the same operations, the same bits
    net, pcomm = on_self_and_all(pack)[1]
    H = stability.active_hessian(net)
    op = H.product(pcomm)
    try:
        v = lowest.start_rows(H.edges.ids, H.d, 3).ravel()
        assert kernels.library() is not None, "the compiled kernels are part of the setup"
        compiled = op.apply(v)
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(kernels, "library", lambda: None)
            assert np.array_equal(op.apply(v), compiled)
    finally:
        op.destroy()
    D, active = dense_active(pack)
    v = lowest.start_rows(active, pack.d, 3).ravel()
    ref = D @ v
    assert np.abs(w_one.ravel() - ref).max() <= 1e-13 * np.abs(D).sum(axis=1).max() * \
        np.abs(v).max()


@pytest.mark.parametrize("settings, root", [(LANCZOS, None), (INERTIA, None), (INERTIA, 0)],
                         ids=["lanczos witness", "inertia, root sinvert", "inertia, lanczos"])
def test_saddle_escape_is_the_same_bits_on_any_number_of_ranks(settings, root):
    """A saddle (contacts opened along the soft mode): the check's verdict, shift, lowest Ritz
    value and steps, the escape direction with its eigenvalue (the Lanczos witness; after an
    exact count shift-and-invert on the first rank, or with -stability_auto_max_dof 0 the
    Lanczos vector converged) and the escape candidates along it, with their energies, are the
    one-rank ones bit for bit on all ranks."""
    pack = saddles.along_soft_mode(read_packing(os.path.join(DATA, STABLE[0])))
    opts = env.petsc().Options()
    if root is not None:
        opts["stability_auto_max_dof"] = root
    got = []
    try:
        for net, pcomm in on_self_and_all(pack):
            cur = stability.check(pcomm, net, settings)
            direction, lam = stability.softest_direction(pcomm, net, cur)
            cands = stability.escape_candidates(net, direction)
            trials = stability.LineTrials(net.state, direction, net.alpha, net.eps)
            energies = [trials.energy(t) for t in cands]
            got.append(((cur.n_negative, cur.shift, cur.method, cur.steps, lam, cands,
                         energies), by_id(net, direction)))
    finally:
        if root is not None:
            opts.delValue("stability_auto_max_dof")
    (info_all, dir_all), (info_one, dir_one) = got
    assert info_one[0] >= 1 and info_one[4] < 0.0 and len(info_one[5]) >= 2
    np.testing.assert_equal(info_all, info_one)
    assert np.array_equal(dir_all, dir_one)
    D, _ = dense_active(pack)
    lam, _ = lowest_modes(D, pack.d)
    assert info_one[4] == pytest.approx(lam[0], rel=1e-6)


@pytest.mark.serial
def test_the_same_bits_on_three_ranks():
    """The tests above on 3 ranks (a middle rank: ghosts on both sides)."""
    res = run_on_ranks("test_stability_lanczos.py", 3, "-k", "same_bits and not three")
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
