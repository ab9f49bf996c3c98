"""Hostile sizes and results (docs/explanation/reliability.md, "Sizes and the machine check", "Results"):

- every size option a user can give (moments, probes, bins, k, N, members, samples, subdivide,
  ncut, the kmax grid) has an upper bound with its reason: beyond it one line, before any work
  (hypothesis, derandomised so that both MPI ranks draw the same values);
- the memory/time estimate of pack and run against the machine: refused unless --force,
  ``run --dry-run`` says why;
- dos refuses mixed dimensions, mixed N and duplicated inputs; an undefined D0/omega* is never
  stored as a silent NaN;
- analyze of an all-rattler packing: valid JSON with null; a manifest.json of the wrong
  structure: one line; a broken PETSC_DIR/SLEPC_DIR: one line (subprocess, serial);
- ordered 2D states are flagged by their contact excess, amorphous ones are not.
"""

import contextlib
import io
import json
import os
import shutil
import subprocess
import sys

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from parjam import cli
from conftest import DATA

P2 = os.path.join(DATA, "soft_d2_N64_m0.h5")
EXAMPLES = int(os.environ.get("PARJAM_HYPOTHESIS_EXAMPLES", "25"))
HOSTILE = settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None,
                   suppress_health_check=list(HealthCheck))


def run_cli(argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = cli.main([str(a) for a in argv])
    return rc, out.getvalue(), err.getvalue()


def assert_one_line(rc, err, words=None):
    from mpi4py import MPI

    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert rc != 0, err
    assert "Traceback" not in err, err
    if MPI.COMM_WORLD.Get_rank() == 0 or lines:
        assert len(lines) == 1 and lines[0].startswith("parjam: error: "), err
        assert words is None or words in lines[0], err


def rank():
    from mpi4py import MPI

    return MPI.COMM_WORLD.Get_rank()


@contextlib.contextmanager
def no_work():
    """Reading a packing or spectrum, a pack member, a scene stage or a lengths computation is
    work: forbidden while a size is checked (lengths' --kmax needs the box: it may read)."""
    from parjam import lengths
    from parjam.files import h5md as pio, modes_io
    from parjam.study import members
    from parjam.study.runner import Runner

    def forbidden(*a, **k):
        raise AssertionError("work started before the sizes were checked")

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(pio, "read_packing", forbidden)
        mp.setattr(modes_io, "read_spectrum", forbidden)
        mp.setattr(members, "pack_member", forbidden)
        mp.setattr(Runner, "run", forbidden)
        mp.setattr(lengths, "compute", forbidden)
        yield mp


# --- every size option above (or below) its bound ------------------------------------------
HUGE = st.integers(min_value=10**6 + 1, max_value=10**18)


def _sizes(tmp):
    """option -> (argv of a value, strategy of values out of range)."""
    spec = os.path.join(tmp, "s.h5")
    out = os.path.join(tmp, "o.h5")
    return {
        "modes --k": (lambda v: ["modes", P2, "--k", v, "--out", out],
                      st.one_of(st.integers(max_value=0), st.integers(100_001, 10**18))),
        "modes --bins": (lambda v: ["modes", P2, "--k", 3, "--bins", v, "--out", out],
                         st.one_of(st.integers(max_value=0), HUGE)),
        "dos --bins": (lambda v: ["dos", spec, "--bins", v, "--out", out],
                       st.one_of(st.integers(max_value=0), HUGE)),
        "dos --moments": (lambda v: ["dos", P2, "--method", "kpm", "--moments", v, "--out", out],
                          st.one_of(st.integers(max_value=1), st.integers(65_537, 10**18))),
        "dos --probes": (lambda v: ["dos", P2, "--method", "kpm", "--probes", v, "--out", out],
                         st.one_of(st.integers(max_value=0), st.integers(10_001, 10**18))),
        "softmodes --bins": (lambda v: ["softmodes", P2, "--cut", "x=0.5", "--bins", v,
                                        "--out", out], st.one_of(st.integers(max_value=1),
                                                                 st.integers(100_001, 10**18))),
        "softmodes --subdivide": (lambda v: ["softmodes", P2, "--subdivide", v, "--out", out],
                                  st.one_of(st.integers(max_value=0),
                                            st.integers(1001, 10**18))),
        "lengths --k": (lambda v: ["lengths", P2, "--k", v, "--out", out],
                        st.one_of(st.integers(max_value=0), st.integers(100_001, 10**18))),
        "lengths --samples": (lambda v: ["lengths", P2, "--what", "lstar", "--samples", v],
                              st.one_of(st.integers(max_value=0), st.integers(10_001, 10**18))),
        "lengths --kmax": (lambda v: ["lengths", P2, "--what", "structure", "--kmax", v],
                           st.floats(1e4, 1e300)),  # >= 1e9 phases for N = 64, L ~ 8
        "pack --n": (lambda v: ["pack", "--dim", 2, "--n", v, "--out", os.path.join(tmp, "p")],
                     st.one_of(st.integers(max_value=15), st.integers(50_000_001, 10**18))),
        "pack --members": (lambda v: ["pack", "--dim", 2, "--n", 16, "--members", v,
                                      "--out", os.path.join(tmp, "p")],
                           st.one_of(st.integers(max_value=0), st.integers(10**6 + 1, 10**18))),
        "plot --ncut": (lambda v: ["plot", P2, "--ncut", v, "--out",
                                   os.path.join(tmp, "f.png")],
                        st.one_of(st.integers(max_value=0), st.integers(100_001, 10**18))),
    }


SIZE_OPTIONS = sorted(_sizes("/x"))


@HOSTILE
@given(data=st.data())
def test_every_size_option_is_bounded(tmp_path_factory, data):
    tmp = str(tmp_path_factory.mktemp("sizes"))
    option = data.draw(st.sampled_from(SIZE_OPTIONS))
    argv, values = _sizes(tmp)[option]
    value = data.draw(values)
    before = sorted(os.listdir(tmp))
    work = contextlib.nullcontext() if option == "lengths --kmax" else no_work()
    with work:
        rc, _, err = run_cli(argv(value) + ["-q"] * (not option.startswith(("dos", "plot"))))
    assert_one_line(rc, err)
    assert sorted(os.listdir(tmp)) == before


def test_pack_and_run_refuse_plans_that_do_not_fit(tmp_path, monkeypatch):
    """A node of 10 MB: pack N = 16 (estimated ~150 MB) and a tiny scene (50 MB) are refused before
    any work; --dry-run says why; a 1 s limit refuses a plan for its time; --force runs."""
    from parjam import resources

    scene = tmp_path / "s.toml"
    scene.write_text('[[system]]\nd = 2\nN = 16\ndispersity = "bi"\n[protocol]\n'
                     'dphi = [1e-2]\n[ensemble]\nmembers = 1\n[observables]\ncontacts = true\n')
    monkeypatch.setenv("PARJAM_MEMORY_MB", "10")
    pack = ["pack", "--dim", 2, "--n", 16, "--dispersity", "bi", "--dphi", "1e-2", "-q",
            "--out", tmp_path / "p"]
    with no_work():
        rc, _, err = run_cli(pack)
        assert_one_line(rc, err, "does not fit this machine")
        rc, _, err = run_cli(["run", scene, "--out", tmp_path / "r", "-q"])
        assert_one_line(rc, err, "does not fit this machine")
        for dry in (["run", scene, "--dry-run"], pack + ["--dry-run"]):
            rc, out, err = run_cli(dry)
            assert rc == 0 and (rank() != 0 or "machine check: DOES NOT FIT" in out), out + err
    assert not (tmp_path / "p").exists() and not (tmp_path / "r").exists()
    monkeypatch.setenv("PARJAM_MEMORY_MB", "1e9")
    monkeypatch.setenv("PARJAM_TIME_LIMIT", "1e-3")
    with no_work():
        rc, _, err = run_cli(pack)
        assert_one_line(rc, err, "would take")
    rc, _, err = run_cli(pack + ["--force"])
    assert rc == 0, err
    # the estimate grows with N: 2e7 particles need more than this machine's memory
    monkeypatch.delenv("PARJAM_MEMORY_MB")
    monkeypatch.delenv("PARJAM_TIME_LIMIT")
    avail = resources.available_memory_mb()
    assert avail is None or resources.pack_memory_mb(2e7) > avail
    assert resources.verdict(resources.pack_memory_mb(5e7), 1.0, 1, 1e5, None)
    assert not resources.verdict(resources.pack_memory_mb(1e3), 1.0, 2, 1e4, (10.0, "x"))


def test_the_pack_estimate_covers_the_measured_stability_check():
    """The machine check's pack model against the peaks measured for the stability check alone
    (docs/results/benchmarks.md, 3D, 1 rank; 2D: docs/explanation/scaling.md), within its factor of 2."""
    from parjam import resources

    for n, measured in ((4096, 161), (32768, 896)):  # sizes where the exact fall-back may run
        est = resources.pack_memory_mb(n, 3)
        assert measured <= est <= 2.0 * measured + resources.PACK_BASE_MB, (n, est)
    # above it the check is the Lanczos test alone (parjam.pack.stability): no factor in the
    # estimate, which stays below the factorisation's measured peak at N = 64000
    assert 64000 > resources.PACK_CHECK_EXACT_MAX_N
    assert resources.pack_memory_mb(64000, 3) < 2239
    # 2D: the check is small (579 MB peak at N = 262,144); the engine's 3D per-particle
    # term covers it
    assert 579 <= resources.pack_memory_mb(262144, 2) < resources.pack_memory_mb(262144, 3)


# --- dos inputs -------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def spectra(shared_tmp):
    """Spectra (k = 6) of two 2D N = 64 members, one 2D N = 128 and one 3D N = 256 packing,
    and a second spectrum (k = 5) of the first member."""
    d = os.path.join(shared_tmp, "dos-inputs")
    out = {}
    for name, src, k in (("a", "soft_d2_N64_m0.h5", 6), ("b", "soft_d2_N64_m1.h5", 6),
                         ("n128", "soft_d2_N128_m0.h5", 6), ("d3", "soft_d3_N256_m0.h5", 6),
                         ("a5", "soft_d2_N64_m0.h5", 5)):
        out[name] = os.path.join(d, f"{name}.h5")
        rc, _, err = run_cli(["modes", os.path.join(DATA, src), "--k", k, "--out", out[name],
                              "-q"])
        assert rc == 0, err
    return out


def test_dos_refuses_mixed_and_duplicated_inputs(spectra, tmp_path):
    from mpi4py import MPI

    s = spectra
    link = str(tmp_path / "link.h5")
    copy = str(tmp_path / "copy.h5")
    if rank() == 0:
        os.symlink(s["a"], link)
        shutil.copy(s["a"], copy)
    MPI.COMM_WORLD.Barrier()
    out = str(tmp_path / "dos.h5")
    cases = [([s["a"], s["d3"]], "average one dimension"),
             ([s["a"], s["n128"]], "one system size"),
             ([s["a"], s["a"]], "the same file"),
             ([s["a"], link], "the same file"),
             ([s["a"], copy], "identical contents"),
             ([s["a"], s["b"], s["a5"]], "same packing"),
             ([P2, P2, "--method", "kpm"], "the same file"),
             ([P2, os.path.join(DATA, "soft_d2_N128_m0.h5"), "--method", "kpm"],
              "one system size"),
             ([P2, os.path.join(DATA, "soft_d3_N256_m0.h5"), "--method", "kpm"],
              "one dimension"),
             ([s["a"], s["b"], "--plateau", "100,200"], "holds no mode")]
    for args, words in cases:
        rc, _, err = run_cli(["dos"] + args + ["--out", out])
        assert_one_line(rc, err, words)
        assert not os.path.exists(out)
    rc, _, err = run_cli(["dos", s["a"], s["b"], "--out", out])
    assert rc == 0, err
    if rank() == 0:
        with h5py.File(out, "r") as f:
            assert np.isfinite(f["dos"].attrs["omega_star"]) and f["dos"].attrs["n_files"] == 2


def test_modes_flags_an_undefined_omega_star(tmp_path):
    out = tmp_path / "s.h5"
    rc, _, err = run_cli(["modes", P2, "--k", 5, "--plateau", "1,2", "--out", out, "-q"])
    assert rc == 0 and (rank() != 0 or "omega_star undefined" in err), err
    if rank() == 0:
        with h5py.File(out, "r") as f:
            assert f["dos"].attrs["undefined"] == "D0,omega_star"
            assert np.isnan(f["dos"].attrs["omega_star"])
    rc, _, err = run_cli(["modes", P2, "--k", 5, "--out", out, "-q"])
    if rank() == 0:
        with h5py.File(out, "r") as f:
            assert f["dos"].attrs["undefined"] == ""
            assert f["dos"].attrs["omega_star"] > 0


# --- analyze JSON, manifests --------------------------------------------------------------------
def _no_nan(text):
    def refuse(token):
        raise ValueError(f"invalid JSON token {token}")

    return json.loads(text, parse_constant=refuse)


def test_analyze_json_of_an_all_rattler_packing_is_valid(tmp_path):
    """Dilute disks (no contact): every particle a rattler; Nc_iso and friends are null."""
    from mpi4py import MPI

    path = str(tmp_path / "dilute.h5")
    if rank() == 0:
        g = np.stack(np.meshgrid(np.arange(4), np.arange(4)), -1).reshape(-1, 2) * 2.5 + 0.3
        with h5py.File(path, "w") as f:
            f["particles/all/position/value"] = g[None].astype(float)
            f["particles/all/diameter"] = np.ones(16)
            f["particles/all/box/edges"] = np.full(2, 10.0)
    MPI.COMM_WORLD.Barrier()
    path = MPI.COMM_WORLD.bcast(path, root=0)
    rc, out, err = run_cli(["analyze", "--json", path])
    assert rc == 0, err
    if rank() == 0:
        rec = _no_nan(out)
        assert rec["N_active"] == 0 and rec["Nc"] == 0
        for key in ("Nc_iso", "excess", "z", "dz", "max_force_rel"):
            assert rec[key] is None, (key, rec)
    rc, out, err = run_cli(["analyze", path])  # collective: every rank
    assert rank() != 0 or "undefined (every particle is a rattler)" in out, out
    rc, out, _ = run_cli(["analyze", "--json", P2])
    if rank() == 0:
        rec = _no_nan(out)
        assert rec["N_active"] == 59 and rec["excess"] == 0 and rec["max_force_rel"] > 0


BAD_MANIFESTS = [
    ("manifest.json", []),
    ("manifest.json", "text"),
    ("manifest.json", {"format": "parjam-pack-manifest", "parameters": 3}),
    ("manifest.json", {"format": "parjam-pack-manifest", "parameters": None}),
    ("manifest.json", {"format": "parjam-pack-manifest", "parameters": {}, "members": [1, 2]}),
    ("manifest.json", {"format": "parjam-pack-manifest", "parameters": {}, "members": {"x": {}}}),
    ("manifest.json", {"format": "parjam-pack-manifest", "parameters": {},
                       "members": {"0": "abc"}}),
    ("manifest.json", {"format": "parjam-pack-manifest", "parameters": {},
                       "members": {"0": {"../etc/passwd": "0"}}}),
    ("manifest.json", {"format": "parjam-pack-manifest", "parameters": {},
                       "members": {"0": {"a.h5": 5}}}),
    (".manifest.d/member0000.json", []),
    (".manifest.d/member0000.json", {"member": "x", "parameters": {}, "files": {}}),
    (".manifest.d/member0000.json", {"member": -1, "parameters": {}, "files": {}}),
    (".manifest.d/member0000.json", {"member": 0, "parameters": [], "files": {}}),
    (".manifest.d/member0000.json", {"member": 0, "parameters": {}, "files": []}),
]


@pytest.mark.parametrize("name,content", BAD_MANIFESTS)
def test_manifest_of_the_wrong_structure_is_one_line(tmp_path, name, content):
    from mpi4py import MPI

    out = tmp_path / "packs"
    if rank() == 0:
        (out / ".manifest.d").mkdir(parents=True)
        (out / name).write_text(json.dumps(content))
    MPI.COMM_WORLD.Barrier()
    with no_work():
        rc, _, err = run_cli(["pack", "--dim", 2, "--n", 16, "--dphi", "1e-2", "--out", out,
                              "-q"])
    assert_one_line(rc, err)


@pytest.mark.serial
@pytest.mark.parametrize("setting,words", [
    ({"PETSC_DIR": "/nonexistent"}, "PETSC_DIR=/nonexistent is not a directory"),
    ({"SLEPC_DIR": "/nonexistent"}, "SLEPC_DIR=/nonexistent is not a directory"),
    ({"PETSC_DIR": ""}, "PETSC_DIR is set but empty"),
    ({"PETSC_DIR": "{tmp}"}, "holds no petsc4py"),
])
def test_info_diagnoses_a_broken_petsc_dir(tmp_path, setting, words):
    from conftest import subprocess_env

    env = subprocess_env(**{k: v.format(tmp=tmp_path) for k, v in setting.items()})
    r = subprocess.run([sys.executable, "-m", "parjam", "info"], env=env, capture_output=True,
                       text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("parjam: error: ") and words in lines[0], \
        r.stderr


# --- ordered 2D states ------------------------------------------------------------------------
def test_small_ordered_2d_state_is_flagged(tmp_path):
    """2D monodisperse N = 16, seed 0, member 0 jams into the distorted lattice at
    phi_c = 0.84179 (hyperstatic by +9, hexatic order only 0.475): flagged by its contacts;
    the bidisperse test packings (isostatic at dphi = 1e-8) are not."""
    from parjam.files import h5md as pio
    from parjam.net import network, order

    out = tmp_path / "m16"
    rc, _, err = run_cli(["pack", "--dim", 2, "--n", 16, "--dispersity", "mono", "--dphi",
                          "1e-4", "--out", out, "-q"])
    assert rc == 0, err
    if rank() == 0:
        assert "hyperstatic by +9" in err, err
        for name in ("member0000_phi_c.h5", "member0000_dphi1.0e-04.h5"):
            with h5py.File(out / name, "r") as f:
                assert pio.observable(f, "ordered_by_contacts") == 1
                assert pio.observable(f, "crystallised") == 1
                assert pio.observable(f, "hexatic_order_local") < order.CRYSTAL_THRESHOLD
    for n in (64, 128, 256, 512, 1024):
        for m in (0, 1):
            pack = pio.read_packing(os.path.join(DATA, f"soft_d2_N{n}_m{m}.h5"))
            net = network.analyze(pack)
            assert not order.ordered_by_contacts(net, 1e-8), (n, m, net.excess)
    assert order.amorphous_dz_limit(1e-2, 1000) == pytest.approx(0.8 + 0.004)
