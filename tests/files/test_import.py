"""``parjam import``: extended XYZ, LAMMPS data and dump, foreign H5MD in, a parjam packing out
(round trips against the arrays written); ``parjam pack --from`` jams an imported configuration;
bad foreign files end with a one-line error and exit 2."""

import os

import h5py
import numpy as np
import pytest

from parjam import cli, env
from parjam.files import export, h5md
from parjam.net.network import analyze
from parjam.pack.packing import random_packing

MPI = env.petsc().COMM_WORLD.tompi4py()


@pytest.fixture
def shared_dir(tmp_path):
    return MPI.bcast(str(tmp_path))


def _pack(d=2, n=64, phi=0.84, seed=5):
    return random_packing(d, n, phi, 2.0, "bi", 1.4, np.random.default_rng(seed))


def _on_rank0(fn, *args):
    if MPI.Get_rank() == 0:
        fn(*args)
    MPI.Barrier()


def _import(args):
    code = cli.main(["import", *args])
    MPI.Barrier()
    return code


def test_extxyz_round_trip(shared_dir):
    pack = _pack(3, 60, 0.6)
    xyz, out = os.path.join(shared_dir, "a.xyz"), os.path.join(shared_dir, "a.h5")
    _on_rank0(export.write_extxyz, xyz, pack, analyze(pack).rattler)
    assert _import([xyz, "--out", out]) == 0
    back = h5md.read_packing(out)
    assert np.array_equal(back.pos, pack.pos) and np.array_equal(back.diam, pack.diam)
    assert back.L == pack.L and back.alpha == pack.alpha
    assert np.array_equal(back.meta["species"], pack.meta["species"])
    assert back.meta["source_format"] == "extxyz" and back.meta["length_scale"] == 1.0
    with h5py.File(out) as f:
        assert f["parameters"].attrs["protocol"] == "imported"
        assert h5md.observable(f, "phi") == pytest.approx(pack.phi, rel=1e-14)


def _lammps_data(path, pos, diam, types, L, style, lo=-1.5, shuffle=None):
    n, d = pos.shape
    pos3 = np.zeros((n, 3))
    pos3[:, :d] = pos
    order = np.arange(n) if shuffle is None else shuffle
    with open(path, "w") as fh:
        fh.write("LAMMPS data file via write_data\n\n")
        fh.write(f"{n} atoms\n{types.max()} atom types\n\n")
        for a in "xyz":
            hi = lo + (L if (a != "z" or d == 3) else 0.5)
            fh.write(f"{lo:.17g} {hi:.17g} {a}lo {a}hi\n")
        fh.write(f"\nAtoms # {style}\n\n")
        for k in order:
            x = pos3[k] + [lo, lo, lo if d == 3 else 0.0]
            cols = [k + 1, types[k]] + ([diam[k], 1.0] if style == "sphere" else [])
            fh.write(" ".join(str(c) for c in cols)
                     + f" {x[0]:.17g} {x[1]:.17g} {x[2]:.17g} 0 0 0\n")
        fh.write("\nVelocities\n\n" + "".join(f"{k + 1} 0 0 0\n" for k in range(n)))


@pytest.mark.parametrize("style", ["sphere", "atomic"])
def test_lammps_data_round_trip(shared_dir, style):
    """Lengths in another unit (diameters 2 and 2.8): rescaled by 1/2; ids shuffled; 2D."""
    pack = _pack()
    scale = 2.0
    types = pack.meta["species"] + 1
    data, out = os.path.join(shared_dir, f"{style}.data"), os.path.join(shared_dir, "l.h5")
    shuffle = np.random.default_rng(0).permutation(pack.n)
    _on_rank0(_lammps_data, data, pack.pos * scale, pack.diam * scale, types, pack.L * scale,
              style, -1.5, shuffle)
    extra = ["--diameters", "2", "2.8"] if style == "atomic" else []
    assert _import([data, "--out", out, *extra]) == 0
    back = h5md.read_packing(out)
    assert back.d == 2 and back.n == pack.n
    assert back.L == pytest.approx(pack.L, rel=1e-14)
    assert np.allclose(back.pos, pack.pos, rtol=0, atol=1e-12 * pack.L)
    assert np.allclose(back.diam, pack.diam, rtol=1e-14)
    assert np.array_equal(back.meta["species"], types)
    assert back.meta["length_scale"] == pytest.approx(0.5, rel=1e-15)


def test_lammps_dump_and_foreign_h5md(shared_dir):
    pack = _pack(3, 60, 0.6, seed=7)
    dump, out = os.path.join(shared_dir, "t.lammpstrj"), os.path.join(shared_dir, "t.h5")
    L = pack.L

    def write_dump():
        with open(dump, "w") as fh:
            for step, pos in ((0, np.zeros_like(pack.pos) + 0.5), (100, pack.pos)):
                fh.write(f"ITEM: TIMESTEP\n{step}\nITEM: NUMBER OF ATOMS\n{pack.n}\n"
                         f"ITEM: BOX BOUNDS pp pp pp\n" + f"0 {L:.17g}\n" * 3
                         + "ITEM: ATOMS id type xs ys zs radius\n")
                for k in range(pack.n):
                    s = pos[k] / L
                    fh.write(f"{k + 1} {pack.meta['species'][k] + 1} {s[0]:.17g} {s[1]:.17g} "
                             f"{s[2]:.17g} {pack.diam[k] / 2:.17g}\n")

    _on_rank0(write_dump)
    assert _import([dump, "--out", out]) == 0  # the last snapshot
    back = h5md.read_packing(out)
    assert np.allclose(back.pos, pack.pos, rtol=0, atol=1e-13 * L)
    assert np.array_equal(back.diam, pack.diam)

    foreign, out2 = os.path.join(shared_dir, "md.h5"), os.path.join(shared_dir, "md.out.h5")

    def write_h5md():  # the layout of MDAnalysis's H5MDWriter: group "trajectory", (3, 3) box
        with h5py.File(foreign, "w") as f:
            g = f.create_group("particles/trajectory")
            box = g.create_group("box")
            box.attrs["dimension"] = 3
            box.attrs["boundary"] = np.array([b"periodic"] * 3)
            box.create_dataset("edges/value", data=np.array([np.eye(3) * L] * 2))
            g.create_dataset("position/value", data=np.stack([pack.pos * 0.9, pack.pos]))
            g.create_dataset("radius", data=pack.diam / 2)
            g.create_dataset("species", data=pack.meta["species"])

    _on_rank0(write_h5md)
    assert _import([foreign, "--out", out2]) == 0
    back = h5md.read_packing(out2)
    assert np.array_equal(back.pos, h5md.read_packing(out).pos)
    assert np.array_equal(back.meta["species"], pack.meta["species"])


BAD = {
    "truncated.xyz": "10\nLattice=\"4 0 0 0 4 0 0 0 4\" Properties=pos:R:3\n0 0 0\n",
    "triclinic.xyz": "2\nLattice=\"4 1 0 0 4 0 0 0 4\" Properties=pos:R:3:radius:R:1\n"
                     "0 0 0 0.5\n2 2 2 0.5\n",
    "nobox.xyz": "2\nProperties=pos:R:3:radius:R:1\n0 0 0 0.5\n2 2 2 0.5\n",
    "noatoms.data": "header\n\n2 atoms\n0 4 xlo xhi\n0 4 ylo yhi\n0 4 zlo zhi\n",
    "cuboid.data": "header\n\n2 atoms\n0 4 xlo xhi\n0 5 ylo yhi\n0 4 zlo zhi\n\nAtoms # sphere\n\n"
                   "1 1 1 1 0 0 0\n2 1 1 1 2 2 2\n",
    "twotypes.data": "header\n\n2 atoms\n0 4 xlo xhi\n0 4 ylo yhi\n0 4 zlo zhi\n\nAtoms # atomic\n\n"
                     "1 1 0 0 0\n2 2 2 2 2\n",
    "garbage.dump": "ITEM: TIMESTEP\n0\nITEM: NUMBER OF ATOMS\nmany\n",
    # no particles (a StopIteration traceback before), non-periodic or impossible
    # extended XYZ headers, and 7 columns under a bare Atoms header (sphere or full?)
    "zeroatoms.data": "header\n\n0 atoms\n0 4 xlo xhi\n0 4 ylo yhi\n0 4 zlo zhi\n\nAtoms\n\n",
    "negatoms.data": "header\n\n-3 atoms\n0 4 xlo xhi\n0 4 ylo yhi\n0 4 zlo zhi\n\nAtoms\n\n"
                     "1 1 0 0 0\n",
    "barefull.data": "header\n\n2 atoms\n1 atom types\n0 4 xlo xhi\n0 4 ylo yhi\n0 4 zlo zhi\n"
                     "\nAtoms\n\n1 1 1 0.0 0 0 0\n2 1 1 0.0 2 2 2\n",
    "fixedz.data": "header\n\n2 atoms\n0 4 xlo xhi\n0 4 ylo yhi\n0 4 zlo zhi\npp pp ff\n\n"
                   "Atoms # sphere\n\n1 1 1 1 0 0 0\n2 1 1 1 2 2 2\n",
    "nopbc.xyz": "2\nLattice=\"4 0 0 0 4 0 0 0 4\" Properties=pos:R:3:radius:R:1 pbc=\"F F F\"\n"
                 "0 0 0 0.5\n2 2 2 0.5\n",
    "flatz.xyz": "2\nLattice=\"4 0 0 0 4 0 0 0 4\" Properties=pos:R:3:radius:R:1 pbc=\"T T F\"\n"
                 "0 0 0 0.5\n2 2 2 0.5\n",
    "dim7.xyz": "2\nLattice=\"4 0 0 0 4 0 0 0 4\" Properties=pos:R:3:radius:R:1 dimension=7\n"
                "0 0 0 0.5\n2 2 2 0.5\n",
    # 27 unit spheres on a cubic lattice in a box of 2.3: phi = 1.16 (the issue's 1.0037)
    "dense.xyz": "27\nLattice=\"2.3 0 0 0 2.3 0 0 0 2.3\" Properties=pos:R:3:radius:R:1\n" + "".join(
        f"{a * 2.3 / 3} {b * 2.3 / 3} {c * 2.3 / 3} 0.5\n" for a in range(3) for b in range(3)
        for c in range(3)),
    "notreally.h5": "plain text\n",
    "unknown.pdb": "ATOM\n",
}


def test_bad_foreign_files_one_line_errors(shared_dir, capsys):
    def write_all():
        for name, text in BAD.items():
            with open(os.path.join(shared_dir, name), "w") as fh:
                fh.write(text)

    _on_rank0(write_all)
    for name in BAD:
        path = os.path.join(shared_dir, name)
        out = os.path.join(shared_dir, name + ".out.h5")
        capsys.readouterr()
        assert _import([path, "--out", out]) == 2, name
        err = capsys.readouterr().err
        if MPI.Get_rank() == 0:
            lines = err.strip().splitlines()
            assert len(lines) == 1 and lines[0].startswith("parjam: error: "), (name, err)
            assert name in lines[0] and "Traceback" not in err
        assert not os.path.exists(out)


REASONS = {"zeroatoms.data": "0 atoms: a packing needs particles",
           "negatoms.data": "-3 atoms: a packing needs particles",
           "barefull.data": "7 columns: full or sphere? name the style",
           "fixedz.data": "boundaries pp pp ff; parjam needs a periodic box",
           "nopbc.xyz": "not periodic along x and y",
           "flatz.xyz": "not periodic along z",
           "dim7.xyz": "dimension=7: parjam packings are 2D or 3D",
           "dense.xyz": "phi = 0.0"}


def test_issue36_importer_cases_say_why(tmp_path):
    """Each hostile file of the third hostile round is refused with its reason (the bare full-style header used
    to be read as sphere, pbc="F F F" as a 2D packing, dimension=7 accepted).  The reader itself,
    each rank on its own file."""
    from parjam.errors import ParjamError
    from parjam.files import importer

    for name, why in REASONS.items():
        path = tmp_path / f"r{MPI.Get_rank()}-{name}"
        path.write_text(BAD[name])
        with pytest.raises(ParjamError) as exc:
            importer.load(str(path))
        if name == "dense.xyz":
            assert "phi = 1.16193 lies outside [0.05, 1) in 3D" in str(exc.value)
            assert "`parjam pack --from` starts only from that range" in str(exc.value)
        else:
            assert why in str(exc.value), (name, str(exc.value))


def test_import_and_pack_from_refuse_the_same_volume_fraction(shared_dir, capsys):
    """phi = 27 (pi/6) / 2.3^3 = 1.162: `import` refuses it (it used to write it with a note)
    and `pack --from` refuses the same configuration written by parjam itself."""
    from parjam.net.system import Packing

    xyz = os.path.join(shared_dir, "dense.xyz")
    h5 = os.path.join(shared_dir, "dense.h5")
    out = os.path.join(shared_dir, "dense.out.h5")

    def write():
        with open(xyz, "w") as fh:
            fh.write(BAD["dense.xyz"])
        rows = np.array([[float(w) for w in ln.split()[:3]]
                         for ln in BAD["dense.xyz"].splitlines()[2:]])
        pack = Packing(rows, np.ones(27), 2.3)
        h5md.write_packing(h5, pack, analyze(pack), {})

    _on_rank0(write)
    capsys.readouterr()
    assert _import([xyz, "--out", out]) == 2 and not os.path.exists(out)
    first = capsys.readouterr().err
    assert cli.main(["pack", "--from", h5, "--dphi", "1e-3", "--out",
                     os.path.join(shared_dir, "packs")]) == 2
    second = capsys.readouterr().err
    if MPI.Get_rank() == 0:
        assert "phi = 1.16193 lies outside [0.05, 1)" in first
        assert "volume fraction 1.16192709" in second and "out of range" in second


def test_bare_atoms_header_read_with_the_style_named(tmp_path):
    """The ambiguous full-style rows read as full when the style is named: types from column 3,
    positions from columns 5-7; read as sphere (as the old reader did silently) the molecule
    id 7 would be the type, outside the header's 2 atom types: refused."""
    from parjam.errors import ParjamError
    from parjam.files import importer

    path = tmp_path / f"r{MPI.Get_rank()}-full.data"
    path.write_text("header\n\n2 atoms\n2 atom types\n0 3 xlo xhi\n0 3 ylo yhi\n0 3 zlo zhi"
                    "\n\nAtoms\n\n1 7 2 0.5 0.5 0.5 0.5\n2 7 1 -0.5 2 2 2\n")
    back = importer.load(str(path), diameters=[1.0, 1.4], atom_style="full")
    assert np.array_equal(back.pos, [[0.5, 0.5, 0.5], [2, 2, 2]])
    assert np.array_equal(back.meta["species"], [2, 1])
    assert np.array_equal(back.diam, [1.4, 1.0])
    with pytest.raises(ParjamError, match=r"Atoms # sphere: types \(column 2\) must lie in 1 .. 2"):
        importer.load(str(path), atom_style="sphere")


def test_h5md_box_edges_as_a_matrix(tmp_path):
    """H5MD allows the box edges as a (D, D) matrix: read when diagonal (fixed or a time series),
    refused when not (it was read as the last row, [0, 0, L])."""
    from parjam.errors import ParjamError
    from parjam.files import importer

    pack = _pack(3, 60, 0.6, seed=7)
    for k, (edges, ok) in enumerate((
            (np.eye(3) * pack.L, True), (np.array([np.eye(3) * pack.L] * 2), True),
            (np.eye(3) * pack.L + np.triu(np.full((3, 3), 0.1), 1), False))):
        path = tmp_path / f"r{MPI.Get_rank()}-{k}.h5"
        with h5py.File(path, "w") as f:
            g = f.create_group("particles/all")
            g.create_group("box").attrs["boundary"] = np.array([b"periodic"] * 3)
            if edges.ndim == 3:
                g.create_dataset("box/edges/value", data=edges)
            else:
                g.create_dataset("box/edges", data=edges)
            g.create_dataset("position", data=pack.pos)
            g.create_dataset("diameter", data=pack.diam)
        if ok:
            back = importer.load(str(path))
            assert back.L == pack.L and np.array_equal(back.pos, pack.pos)
        else:
            with pytest.raises(ParjamError, match="a triclinic box"):
                importer.load(str(path))


@pytest.mark.serial
def test_pack_from_an_imported_lammps_configuration(tmp_path):
    """A random (unjammed) LAMMPS configuration imported, then minimised, brought to phi_c and
    compressed by dphi = 1e-3 with `pack --from`, as a user runs them (processes of their own:
    serial pass only; a member shared by 2 ranks is tested in test_packing)."""
    import subprocess
    import sys

    from conftest import subprocess_env

    pack = _pack(2, 24, 0.80, seed=11)
    data, imported = str(tmp_path / "start.data"), str(tmp_path / "start.h5")
    out = str(tmp_path / "packs")
    _lammps_data(data, pack.pos, pack.diam, pack.meta["species"] + 1, pack.L, "sphere")

    def parjam(*args):
        return subprocess.run([sys.executable, "-m", "parjam", *args], env=subprocess_env(),
                              capture_output=True, text=True, timeout=600)

    r = parjam("import", data, "--out", imported)
    assert r.returncode == 0, r.stderr
    r = parjam("pack", "--from", imported, "--dphi", "1e-3", "--out", out, "-q",
               "--checkpoint-every", "0")
    assert r.returncode == 0, r.stderr
    phic = h5md.read_packing(os.path.join(out, "member0000_phi_c.h5"))
    top = h5md.read_packing(os.path.join(out, "member0000_dphi1.0e-03.h5"))
    phi_c = float(phic.meta["phi_c"])
    assert top.phi == pytest.approx(phi_c + 1e-3, rel=1e-12)
    assert np.array_equal(top.diam, pack.diam)
    assert np.array_equal(top.meta["species"], pack.meta["species"] + 1)
    net = analyze(top)
    assert net.max_force <= 1e-12 and net.excess >= 0  # jammed, in force balance
    with h5py.File(os.path.join(out, "member0000_phi_c.h5")) as f:
        assert 1e-16 <= h5md.observable(f, "energy_per_particle") <= 2e-16
    r = parjam("pack", "--from", imported, "--members", "2", "--out", out)
    assert r.returncode == 2 and r.stderr.strip() == (
        "parjam: error: --from starts one configuration: --members must be 1, got 2")
