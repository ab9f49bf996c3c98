"""Units on every dataset (docs/reference/file-format.md, "Units"): the files of `pack`, `modes` and `dos`
are walked dataset by dataset and each must be in the table below, with its unit attribute
(H5MD notation, fixed-length ASCII) or none for a dimensionless one; the H5MD units module is
declared.  A dataset that nobody classified fails the test."""

import os
import re

import h5py
import pytest

from parjam import cli, env

MPI = env.petsc().COMM_WORLD.tompi4py()

#: dataset path (regular expression) -> unit; None: dimensionless (counts, flags, indices,
#: fractions, relative residuals).  {p}: the pressure's unit, epsilon sigma-d.
UNITS = [
    (r"particles/all/box/edges/value", "sigma"),
    (r"particles/all/diameter", "sigma"),
    # MDAnalysis refuses any unit it cannot convert, even with convert_units=False: the
    # positions and their time are in sigma and tau without saying so (file-format.md)
    (r"particles/all/position/(value|time)", None),
    (r"particles/all/(species|rattler)", None),
    (r".*/step", None),
    (r".*/time", "tau"),
    (r"connectivity/(contacts|overlap)", None),
    (r"connectivity/force", "epsilon sigma-1"),
    (r"connectivity/stiffness", "epsilon sigma-2"),
    (r"observables/(pressure|stress_tensor)/value", "{p}"),
    (r"observables/energy_per_particle/value", "epsilon"),
    (r"observables/max_force/value", "epsilon sigma-1"),
    (r"observables/(curvature_shift|lowest_curvature_found)/value", "epsilon sigma-2"),
    (r"observables/(phi|N|N_active|n_rattlers|Nc|Nc_iso|excess|z|dz|dz_iso|max_force_rel|"
     r"hexatic_order_local|hexatic_order_global|crystallised|ordered_by_contacts|stable|"
     r"negative_curvatures|negative_curvatures_found|excess_found|escapes|cycles|dphi_virial|"
     r"dphi_virial_ok)/value", None),
    (r"modes/(rejected/)?eigenvalue", "tau-2"),
    (r"modes/frequency", "tau-1"),
    (r"modes/(rejected/)?error|modes/(participation_ratio|eps_perp|eps_par|eigenvector|"
     r"active_particles)", None),
    (r"dos/(omega|edges)", "tau-1"),
    (r"dos/(density|density_error)", "tau"),
]


def expected(name, d):
    hits = [unit for pattern, unit in UNITS if re.fullmatch(pattern, name)]
    assert hits, f"{name}: a dataset no row of UNITS classifies"
    return None if hits[0] is None else hits[0].replace("{p}", f"epsilon sigma-{d}")


def walk(path, d):
    """Every dataset of a file against UNITS; the names seen."""
    seen = []
    with h5py.File(path, "r") as f:
        units = f["h5md/modules/units"]
        assert list(units.attrs["version"]) == [1, 0]
        assert units.attrs["system"] == b"reduced: sigma epsilon tau"

        def check(name, obj):
            if not isinstance(obj, h5py.Dataset) or name.startswith("h5md"):
                return
            seen.append(name)
            want = expected(name, d)
            got = obj.attrs.get("unit")
            if want is None:
                assert got is None, f"{path}: {name} is dimensionless but says {got!r}"
                return
            assert got == want.encode(), f"{path}: {name} has unit {got!r}, not {want!r}"
            assert h5py.check_string_dtype(obj.attrs.get_id("unit").dtype).length  # fixed

        f.visititems(check)
    return seen


@pytest.mark.parametrize("d", [2, 3])
def test_every_dataset_of_pack_modes_dos_names_its_unit(shared_tmp, d):
    root = os.path.join(shared_tmp, f"units{d}")
    packs = os.path.join(root, "packs")
    assert cli.main(["pack", "--dim", str(d), "--n", "16" if d == 2 else "24", "--dispersity",
                     "bi", "--members", "2", "--dphi", "1e-2", "--out", packs, "-q",
                     "--checkpoint-every", "0"]) == 0
    files = [os.path.join(packs, f"member000{m}_dphi1.0e-02.h5") for m in (0, 1)]
    spectra = [os.path.join(root, f"s{m}.h5") for m in (0, 1)]
    for src, out in zip(files, spectra):
        assert cli.main(["modes", src, "--k", "6", "--out", out, "-q"]) == 0
    dos = os.path.join(root, "dos.h5")
    assert cli.main(["dos", *spectra, "--bins", "4", "--out", dos]) == 0
    MPI.Barrier()
    names = set()
    for path in [*files, os.path.join(packs, "member0000_phi_c.h5"), spectra[0], dos]:
        names.update(walk(path, d))
    # the walk reached every kind of dataset the table names
    for must in ("observables/pressure/value", "connectivity/force", "modes/frequency",
                 "dos/density_error", "particles/all/box/edges/time"):
        assert must in names
