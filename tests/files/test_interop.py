"""Files that other tools open: MDAnalysis reads parjam's packing and spectrum files (H5MD) and
ASE reads `parjam export`'s extended XYZ (every export and client: test_clients.py); positions, box, species and radius are compared with
what h5py reads from the same files.  Older parjam files (plain box edges, scalar observables)
still read.  MDAnalysis and ASE are installed by scripts/setup-env (ci/test-requirements.txt)."""

import os
import warnings

import h5py
import numpy as np
import pytest

from parjam import cli, env
from parjam.files import h5md, modes_io
from parjam.net.network import analyze
from parjam.pack.packing import random_packing

MPI = env.petsc().COMM_WORLD.tompi4py()
REF3D = "tests/data/ref_d3_mono_N128_dphi1e-03.h5"


@pytest.fixture
def shared_dir(tmp_path):
    return MPI.bcast(str(tmp_path))


def _h5(path):
    """Positions, box edges, diameters, species of a parjam file, read with plain h5py."""
    with h5py.File(path, "r") as f:
        part = f["particles/all"]
        return (part["position/value"][-1], part["box/edges/value"][-1], part["diameter"][()],
                part["species"][()])


def _mdanalysis_universe(path, n):
    """The documented call (docs/reference/file-format.md)."""
    import MDAnalysis as mda

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # MDAnalysis warns about the empty topology
        u = mda.Universe.empty(n, trajectory=True)
        u.load_new(path, format="H5MD", convert_units=False)
    return u


def _bidisperse_3d(seed=4):
    pack = random_packing(3, 60, 0.6, 2.0, "bi", 1.4, np.random.default_rng(seed))
    assert set(pack.meta["species"]) == {0, 1}
    return pack


def test_mdanalysis_opens_a_packing_file(tmp_path):
    path = str(tmp_path / "p.h5")
    pack = _bidisperse_3d()
    net = analyze(pack)
    h5md.write_packing(path, pack, net, {"seed": 4})
    pos, edges, diam, species = _h5(path)
    u = _mdanalysis_universe(path, pack.n)
    assert u.trajectory.n_frames == 1
    # MDAnalysis keeps positions in float32
    assert np.allclose(u.atoms.positions, pos, rtol=0, atol=4e-7 * pack.L)
    assert np.allclose(u.dimensions, [*edges, 90, 90, 90], rtol=1e-7)
    data = u.trajectory.ts.data
    assert data["phi"] == pytest.approx(pack.phi, rel=1e-14)
    assert data["pressure"] == pytest.approx(net.pressure, rel=1e-14)
    assert data["dz"] == net.dz and data["dz_iso"] == net.dz_iso
    assert np.array_equal(data["stress_tensor"], net.stress)
    # species and diameters survive the h5py round trip and read_packing
    back = h5md.read_packing(path)
    assert np.array_equal(species, pack.meta["species"])
    assert np.array_equal(back.meta["species"], pack.meta["species"])
    assert np.array_equal(diam, pack.diam) and np.array_equal(back.diam, pack.diam)
    with h5py.File(path, "r") as f:  # the H5MD strings and units
        assert f["h5md/creator"].attrs["name"] == b"parjam"
        assert h5py.check_string_dtype(f["h5md/creator"].attrs.get_id("name").dtype).length
        assert f["h5md"].attrs["version"].dtype.kind == "i"
        assert f["particles/all/box/edges/value"].attrs["unit"] == b"sigma"
        assert f["observables/pressure/value"].attrs["unit"] == b"epsilon sigma-3"
        assert f["observables/pressure/step"][()].dtype.kind == "i"


def test_mdanalysis_opens_a_spectrum_file(shared_dir):
    pack_path = os.path.join(shared_dir, "p.h5")
    out = os.path.join(shared_dir, "s.h5")
    if MPI.Get_rank() == 0:
        pack = h5md.read_packing(REF3D)
        h5md.write_packing(pack_path, pack, analyze(pack), {})
    MPI.Barrier()
    assert cli.main(["modes", pack_path, "--k", "6", "--method", "dense", "--out", out,
                     "-q"]) == 0
    MPI.Barrier()
    ref = h5md.read_packing(pack_path)
    pos, edges, _, _ = _h5(out)
    assert np.array_equal(pos, ref.pos) and np.all(edges == ref.L)
    u = _mdanalysis_universe(out, ref.n)
    assert np.allclose(u.atoms.positions, ref.pos, rtol=0, atol=4e-7 * ref.L)
    assert np.allclose(u.dimensions[:3], ref.L, rtol=1e-7)
    spec = modes_io.read_spectrum(out)
    assert len(spec["eigenvalue"]) == 6


@pytest.mark.parametrize("d", [2, 3])
def test_ase_reads_exported_xyz_with_species_radius_rattlers(tmp_path, d):
    import ase.io

    from parjam.files import export

    pack = (random_packing(2, 80, 0.8, 2.0, "bi", 1.4, np.random.default_rng(1)) if d == 2
            else _bidisperse_3d())
    net = analyze(pack)
    h5 = str(tmp_path / f"p{MPI.Get_rank()}.h5")
    h5md.write_packing(h5, pack, net, {})
    back = h5md.read_packing(h5)  # species must survive the file
    xyz = str(tmp_path / f"p{MPI.Get_rank()}.xyz")
    export.write_extxyz(xyz, back, analyze(back).rattler)
    pos, edges, diam, species = _h5(h5)
    atoms = ase.io.read(xyz, format="extxyz", parallel=False)
    assert len(atoms) == pack.n
    assert np.array_equal(atoms.positions[:, :d], pos)
    assert np.allclose(np.diag(atoms.cell)[:d], edges, rtol=1e-15)
    assert list(atoms.pbc) == [True, True, d == 3]
    assert np.array_equal(atoms.arrays["type"], species + 1)  # types count from 1
    assert set(atoms.get_chemical_symbols()) == {"H", "He"}  # two species stay two (Z = type)
    assert np.array_equal(atoms.arrays["radius"], diam / 2)
    assert np.array_equal(atoms.arrays["rattler"], net.rattler.astype(int))
    assert atoms.info["phi"] == pytest.approx(pack.phi, rel=1e-15)


def test_older_parjam_files_still_read(tmp_path):
    """Files written before the H5MD time-series layout: plain box edges, scalar observables."""
    from parjam.study.members import rows_from_files

    pack = h5md.read_packing(REF3D)
    net = analyze(pack)
    path = tmp_path / "member0000_dphi1.0e-03.h5"
    with h5py.File(path, "w") as f:
        part = f.create_group("particles/all")
        part.create_dataset("box/edges", data=np.full(3, pack.L))
        part.create_dataset("position/value", data=pack.pos[None])
        part.create_dataset("diameter", data=pack.diam)
        obs = f.create_group("observables")
        for key, val in net.summary().items():
            obs.create_dataset(key, data=val)
        f.create_group("parameters").attrs.update({"alpha": 2.0, "state": "dphi1.0e-03"})
    back = h5md.read_packing(path)
    assert np.array_equal(back.pos, pack.pos) and back.L == pack.L
    (row,) = rows_from_files(str(tmp_path), 0, [path.name])
    assert row["pressure"] == net.pressure and row["z"] == net.z
