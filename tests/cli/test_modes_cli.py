"""``parjam modes`` and ``parjam dos``: the spectrum file, full vs relaxed in one command, the
ensemble D(omega), and bad input (one-line error, non-zero exit, no file)."""

import os
import subprocess
import sys

import h5py
import numpy as np
import pytest

from parjam import cli, env
from parjam.files import h5md, modes_io
from parjam.net import network
from parjam.vib import solver_choice
from parjam.pack.packing import random_packing
from parjam.net.system import Packing

PETSc = env.petsc()
MPI = PETSc.COMM_WORLD.tompi4py()
REF = "tests/data/ref_d3_mono_N128_dphi1e-03"
REF2D = "tests/data/ref_d2_bi_N128_dphi1e-03"


@pytest.fixture
def shared_dir(tmp_path):
    """One directory for all ranks (rank 0's tmp_path)."""
    return MPI.bcast(str(tmp_path))


def run_main(args):
    """The command line in-process on every rank; the exit code."""
    return cli.main(list(args))


def test_modes_writes_the_documented_file(shared_dir):
    out = os.path.join(shared_dir, "s.h5")
    code = run_main(["modes", f"{REF}.h5", "--k", "25", "--method", "sinvert", "--out", out,
                     "-q"])
    assert code == 0
    MPI.Barrier()
    f = modes_io.read_spectrum(out)
    ref = np.load(f"{REF}.spectrum.npz")["full"][3:28]
    assert np.allclose(f["eigenvalue"], ref, rtol=1e-8, atol=0)
    assert np.allclose(f["frequency"], np.sqrt(ref), rtol=1e-8)
    assert np.all(f["error"] <= 1e-10)
    assert "eigenvector" not in f  # only when asked for
    a = f["attrs"]
    assert a["matrix"] == "full" and a["method"] == "sinvert" and a["ranks"] == MPI.Get_size()
    assert a["translations_deflated"] and a["rattlers_removed"] and a["complete"]
    assert a["packing_sha256"] == h5md.sha256(f"{REF}.h5")
    assert a["n_modes_total"] == 3 * 125 - 3 and not a["unstable"]
    assert np.isclose(a["target"], -1e-9 * a["norm_inf"])
    assert len(f["active_particles"]) == 125
    dos = f["dos"]
    assert np.isclose(np.sum(dos["density"] * np.diff(dos["edges"])), 25 / 372)
    with h5py.File(out, "r") as h:
        assert tuple(h["h5md"].attrs["version"]) == (1, 1)
        assert h["dos"].attrs["binning"] == "linear" and h["dos"].attrs["D0"] > 0


def test_vectors_and_window_and_compare(shared_dir):
    """--matrix full relaxed in one command (Fig. 'compare'), a window by slicing, vectors."""
    out = os.path.join(shared_dir, "w.h5")
    png = os.path.join(shared_dir, "w.png")
    code = run_main(["modes", f"{REF2D}.h5", "--matrix", "full", "relaxed", "--window", "0,0.3",
                     "--method", "slice", "--vectors", "--log-bins", "--bins", "8", "--out", out,
                     "--plot", png, "-q"])
    assert code == 0
    MPI.Barrier()
    ref = np.load(f"{REF2D}.spectrum.npz")
    for kind in ("full", "relaxed"):
        f = modes_io.read_spectrum(os.path.join(shared_dir, f"w.{kind}.h5"))
        expect = ref[kind][(ref[kind] > 1e-8) & (ref[kind] <= 0.09)]
        assert np.allclose(f["eigenvalue"], expect, rtol=1e-7)
        assert f["eigenvector"].shape == (len(expect), 120, 2)
        assert f["attrs"]["method"] == "slice"
        assert np.allclose(f["attrs"]["interval_lambda"][1], 0.09)
    assert os.path.getsize(png) > 10_000


def test_dos_ensemble_average(shared_dir):
    outs = []
    for name in ("ref_d3_mono_N128_dphi1e-03", "ref_d3_mono_N128_dphi1e-06"):
        out = os.path.join(shared_dir, f"{name}.h5")
        assert run_main(["modes", f"tests/data/{name}.h5", "--k", "372", "--method", "dense",
                         "--out", out, "-q"]) == 0
        outs.append(out)
    MPI.Barrier()  # every rank reads the files rank 0 wrote
    ens = os.path.join(shared_dir, "ens.h5")
    assert run_main(["dos", *outs, "--bins", "20", "--out", ens]) == 0
    MPI.Barrier()
    with h5py.File(ens, "r") as h:
        dens, err, edges = h["dos/density"][()], h["dos/density_error"][()], h["dos/edges"][()]
        d0_each = h["dos"].attrs["D0_each"]
        assert h["dos"].attrs["n_files"] == 2
    single = [np.histogram(np.sqrt(np.load(o.replace(os.path.dirname(o), "tests/data")
                                           .replace(".h5", ".spectrum.npz"))["full"][3:]),
                           bins=edges)[0] / (372 * np.diff(edges)) for o in outs]
    assert np.allclose(dens, np.mean(single, axis=0))
    assert np.allclose(err, np.std(single, axis=0, ddof=1) / np.sqrt(2))
    assert np.all(d0_each > 0)


def test_modes_rejects_a_second_kind_in_dos(shared_dir):
    a = os.path.join(shared_dir, "a.h5")
    assert run_main(["modes", f"{REF}.h5", "--matrix", "full", "relaxed", "--k", "5", "--out", a,
                     "-q"]) == 0
    MPI.Barrier()
    code = run_main(["dos", os.path.join(shared_dir, "a.full.h5"),
                     os.path.join(shared_dir, "a.relaxed.h5"), "--out",
                     os.path.join(shared_dir, "x.h5")])
    assert code != 0 and not os.path.exists(os.path.join(shared_dir, "x.h5"))


# --- bad input through the real command line (subprocesses: serial pass only) ---------------
def parjam(*args):
    return subprocess.run([sys.executable, "-m", "parjam", *args], capture_output=True,
                          text=True, timeout=120)


@pytest.fixture(scope="module")
def bad_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("bad")
    dilute = random_packing(3, 64, 0.05, rng=np.random.default_rng(1))
    h5md.write_packing(d / "unjammed.h5", dilute, network.analyze(dilute), {})
    g = (np.arange(4) + 0.5) * 1.5
    lattice = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    apart = Packing(lattice, np.ones(64), 6.0)
    h5md.write_packing(d / "nocontacts.h5", apart, network.analyze(apart), {})
    with h5py.File(d / "garbage.h5", "w") as f:
        f.create_dataset("x", data=[1, 2])
    return d


@pytest.mark.serial
@pytest.mark.parametrize("args, message", [
    ([f"{REF}.h5", "--k", "373"], "exceeds the 372 non-translational modes"),
    ([f"{REF}.h5", "--window", "0.3,0.1"], "empty frequency window"),
    ([f"{REF}.h5", "--window", "0.001,0.002", "--method", "slice"], "holds no eigenvalue"),
    ([f"{REF}.h5", "--window", "abc"], "--window must be two numbers"),
    ([f"{REF}.h5", "--k", "0"], "--k must be >= 1"),
    (["BAD/unjammed.h5", "--k", "5"], "unjammed packing"),
    (["BAD/nocontacts.h5", "--k", "5"], "no contacts"),
    (["BAD/garbage.h5", "--k", "5"], "missing dataset"),
    (["BAD/missing.h5", "--k", "5"], "no such file"),
])
def test_bad_input_one_line_error(bad_files, tmp_path, args, message):
    args = [a.replace("BAD", str(bad_files)) for a in args]
    out = tmp_path / "o.h5"
    res = parjam("modes", *args, "--out", str(out), "-q")
    assert res.returncode != 0
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("parjam: error:") and message in lines[0], \
        res.stderr
    assert not out.exists() and not list(tmp_path.glob(".o.h5*"))


@pytest.mark.serial
def test_unconverged_run_exits_non_zero_with_a_warning(tmp_path):
    out = tmp_path / "u.h5"
    res = parjam("modes", f"{REF}.h5", "--k", "30", "--method", "sinvert", "--tol", "1e-15",
                 "--out", str(out), "-q", "-modes_eps_max_it", "1", "-modes_eps_ncv", "35")
    assert res.returncode == 4, res.stderr
    assert "warning" in res.stderr and "pairs reached residual" in res.stderr
    f = modes_io.read_spectrum(out)
    assert not f["attrs"]["complete"] and np.all(f["error"] <= 1e-15)


@pytest.mark.serial
def test_two_ranks_write_the_same_spectrum(tmp_path):
    """mpirun -n 2 parjam modes gives the 1-rank spectrum (file written once, by rank 0)."""
    from shutil import which

    mpirun = os.environ.get("PARJAM_MPIRUN", "mpirun --oversubscribe").split()
    if which(mpirun[0]) is None:
        pytest.fail("mpirun not found")
    env_vars = dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
                    OMPI_MCA_rmaps_base_oversubscribe="1", OMP_NUM_THREADS="1")
    outs = []
    for n in (1, 2):
        out = tmp_path / f"r{n}.h5"
        res = subprocess.run(mpirun + ["-n", str(n), sys.executable, "-m", "parjam", "modes",
                                       f"{REF2D}.h5", "--k", "30", "--method", "sinvert",
                                       "--out", str(out), "-q"],
                             capture_output=True, text=True, timeout=300, env=env_vars)
        assert res.returncode == 0, res.stderr
        outs.append(modes_io.read_spectrum(out))
    assert outs[1]["attrs"]["ranks"] == 2
    assert np.allclose(outs[0]["eigenvalue"], outs[1]["eigenvalue"], rtol=1e-11)
    assert np.allclose(outs[0]["participation_ratio"], outs[1]["participation_ratio"], rtol=1e-7)
    assert solver_choice.PARTIAL_DENSE_MAX_DOF >= 240  # auto would have chosen dense here
