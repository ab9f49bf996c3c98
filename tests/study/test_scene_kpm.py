"""D(omega) by KPM in scenes (``dos = { method = "kpm" }``, parjam.vib.kpm_dos): parsing, stage keys
of the dense scenes unchanged, D0 and omega* against dense LAPACK, the partial-spectrum omega*
(omega_AM) with the KPM plateau, and 1 rank against all ranks.  Serially and under
mpirun -n 2."""

import os

import numpy as np
import pytest

from parjam.testing.reference import dense_system
from parjam.vib.dense import dense_matrix
from parjam import env
from parjam.files import h5md, rowio
from parjam.net import active
from parjam.vib import kpm_dos, observables, spectrum
from parjam.errors import ParjamError
from parjam.progress import Progress
from parjam.study import plan as study_plan
from parjam.files import stagefile
from parjam.study import runner as runmod
from parjam.study import scene as sc
from parjam.study.summary import read_summary
from conftest import DATA

BASE = """
[[system]]
d = 3
N = 256
[protocol]
dphi = [1e-3, 1e-2]
[ensemble]
members = 2
seed = 5
[observables]
"""


@pytest.mark.parametrize("obs, key", [
    ("dos = { moments = 512 }", "moments"),
    ("dos = { method = 'lanczos' }", "method"),
    ("dos = { method = 'kpm', window = [0.0, 1.0] }", "window"),
    ("dos = { method = 'kpm', moments = 'many' }", "moments"),
    ("dos = { method = 'kpm', moments = 8 }", "moments"),
    ("dos = { method = 'kpm', probes = 0 }", "probes"),
])
def test_kpm_options_are_checked(obs, key):
    with pytest.raises(ParjamError, match=key):
        sc.loads(BASE + obs)


def test_dense_stage_keys_do_not_change_and_kpm_needs_no_eigensolver():
    """method = "dense" (the default, given or not) plans and keys exactly as before; KPM
    changes only the spectrum and summary keys, and a KPM-only state has solver "kpm"."""
    keys = [{(st.kind, st.matrix): st.key for st in study_plan.plan(sc.loads(BASE + obs))}
            for obs in ("dos = { matrices = ['full', 'relaxed'] }",
                        "dos = { matrices = ['full', 'relaxed'], method = 'dense' }",
                        "dos = { matrices = ['full', 'relaxed'], method = 'kpm' }")]
    assert keys[0] == keys[1]
    assert keys[2][("pack", None)] == keys[0][("pack", None)]
    assert keys[2][("spectrum", "full")] != keys[0][("spectrum", "full")]
    scene = sc.loads(BASE + "dos = { method = 'kpm', matrices = ['full'] }\n"
                            "omega_star = { matrices = ['full'], k = 40, at = [1e-3] }\n"
                            "[solver]\nsmall_dof = 0\n")
    full = next(st for st in study_plan.plan(scene) if st.kind == "spectrum")
    assert full.params["dphi1.0e-02"]["solver"] == "kpm"
    assert full.params["dphi1.0e-03"]["solver"] == "sinvert"
    assert full.params["dphi1.0e-03"]["kpm"]["moments"] == "auto"


def dense_omega(path, kind):
    system = dense_system(h5md.read_packing(path))
    lam = np.linalg.eigvalsh(dense_matrix(system, kind))[system.d:]
    w = observables.frequency(lam)
    return w[w > 0], system.n_modes


def test_kpm_scene_gives_the_dense_d0_and_omega_star(shared_tmp, world):
    """D0 and omega* of KPM (dphi = 1e-2, resolved) and of the lowest modes with the KPM plateau
    (dphi = 1e-3: omega_AM and omega*_relaxed at N = 10240) against dense LAPACK of the same
    packings, and the summary's D(omega) against the dense histogram."""
    text = BASE + """dos = { method = "kpm", matrices = ["full", "relaxed"], probes = 16, bins = 20 }
omega_star = { matrices = ["full", "relaxed"], k = 80, plateau = "kpm", at = [1e-3] }
[solver]
small_dof = 0
"""
    scene = sc.loads(text, "test.toml")
    out = os.path.join(shared_tmp, "kpm-scene")
    runner = runmod.Runner(scene, study_plan.plan(scene), out, world, Progress(quiet=True))
    assert runner.run() == 0
    summ = read_summary(next(iter(runner.summaries.values())))
    system = scene.systems[0]
    for st in (x for x in runner.stages if x.kind == "spectrum"):
        for m in range(2):
            part = stagefile.read_part(runner.part_path(st, m))
            for lab in ("dphi1.0e-02", "dphi1.0e-03"):
                rec = part[lab]
                w, n_modes = dense_omega(runner.pack_path(system, m, lab), st.matrix)
                d0, wstar, _ = observables.dos_summary(w, n_modes)
                # docs/results/speed-accuracy.md: D0 within 0.1 - 1 % at N = 1024 with 8 - 32 probes;
                # N' ~ 250 has 4x the stochastic error
                assert rec["D0"] == pytest.approx(d0, rel=0.04)
                if lab == "dphi1.0e-02":  # KPM alone, omega* resolved (N = 1024: 3 - 5 %)
                    assert rec["solver"] == "kpm" and rec["kpm_resolved"] == 1
                    assert rec["omega_star"] == pytest.approx(wstar, rel=0.10)
                else:  # the lowest 80 modes with the KPM D0: one mode (~10 %) at most
                    assert rec["solver"] == "sinvert" and len(rec["frequency"]) == 80
                    assert rec["omega_star"] == pytest.approx(wstar, rel=0.12)
        g = summ["dphi1.0e-02"]["spectrum"][st.matrix]["dos"]
        assert np.all(g["kpm_moments"] >= 256) and np.all(g["density_error"] > 0)
        hist = []
        for m in range(2):
            w, n_modes = dense_omega(runner.pack_path(system, m, "dphi1.0e-02"), st.matrix)
            hist.append(observables.density_of_states(w, n_modes, g["edges"])[1])
        l1 = np.sum(np.abs(g["density"] - np.mean(hist, axis=0)) * np.diff(g["edges"]))
        assert l1 < 0.1, l1  # test_kpm's bound 0.06 + 2 / sqrt(moments x probes), 2 members


def test_kpm_moments_do_not_depend_on_the_ranks(world):
    """The same KPM record (auto moments) from this rank's rows of a file on all ranks as from
    the whole packing on one rank."""
    path = os.path.join(DATA, "ref_d3_mono_N128_dphi1e-03.h5")
    rows = rowio.read_rows(world, path)
    dist = spectrum.distributed_system(active.from_rows(world, rows))
    a = kpm_dos.to_record(kpm_dos.compute(world, dist, "relaxed", "auto", 2, 512))
    self_comm = env.petsc().COMM_SELF
    serial = spectrum.system_of(self_comm, h5md.read_packing(path))
    b = kpm_dos.to_record(kpm_dos.compute(self_comm, serial, "relaxed", "auto", 2, 512))
    assert a["kpm_n_moments"] == b["kpm_n_moments"]
    np.testing.assert_allclose(a["kpm_moments"], b["kpm_moments"], atol=1e-10)
    assert a["kpm_D0"] == pytest.approx(b["kpm_D0"], rel=1e-9)


def test_lowest_modes_with_sums_and_kpm_on_distributed_vectors(world):
    """One state's record as the N = 10240 scene makes it (trans: the k lowest modes with their
    per-mode sums, D0 from the KPM moments, the vectors stored), from this rank's rows: the
    eigenvalues, eps_perp, eps_par and the gathered vectors (in particle-id order) against the
    dense modes of the whole packing."""
    from parjam.study.records import spectrum_record

    path = os.path.join(DATA, "ref_d3_mono_N128_dphi1e-03.h5")
    req = {"all": False, "k": 20, "window": None, "per_mode": True, "vectors": True,
           "solver": "sinvert", "kpm": {"moments": 256, "probes": 2, "max_moments": 256}}
    rec = spectrum_record(world, rowio.read_rows(world, path), "full", req, 1e-10)
    self_comm = env.petsc().COMM_SELF
    system = spectrum.system_of(self_comm, h5md.read_packing(path))
    ref = spectrum.compute(self_comm, system, "full", k=20, method="dense", vectors=True)
    ref_vectors = spectrum.vectors_on_root(self_comm, ref)
    np.testing.assert_allclose(rec["eigenvalue"], ref.eigenvalue, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(rec["eps_par"], ref.eps_par, rtol=1e-6, atol=1e-10)
    np.testing.assert_allclose(rec["eps_perp"], ref.eps_perp, rtol=1e-6, atol=1e-10)
    assert rec["plateau_source"] == "kpm" and rec["kpm_n_moments"] == 256
    assert rec["D0"] == rec["kpm_D0"]
    if world.getRank() == 0:  # vectors up to sign, well separated modes only
        v, r = rec["eigenvector"].reshape(20, -1), ref_vectors.reshape(20, -1)
        gap = np.diff(ref.eigenvalue)
        lone = [i for i in range(1, 19) if min(gap[i - 1], gap[i]) > 1e-3 * ref.eigenvalue[i]]
        overlap = np.abs(np.sum(v * r, axis=1))[lone]
        np.testing.assert_allclose(overlap, 1.0, atol=1e-6)
