"""HDF5 files in the H5MD 1.1 layout (docs/reference/file-format.md) through h5py.

Writes are atomic: a file is written under a temporary name in the same directory and renamed
into place only when complete, so a killed run never leaves a truncated file that looks valid.
Only the caller that owns a file (rank 0 of the group that computed it) writes it.
"""

import hashlib
import json
import os
import sys

import h5py
import numpy as np
from parjam import __version__, env
from parjam.errors import ParjamError
from parjam.files import inputs, outputs
from parjam.net.system import Packing, coinciding_pairs, wrap


def atomic_h5(path):
    """Open ``path`` for writing: an in-memory HDF5 file whose image is written atomically when
    the block succeeds (parjam.files.outputs: the output policy; a full disk is one line, never a
    partial file)."""
    return outputs.atomic_h5(path)


def write_h5md_header(f, provenance=None):
    """The /h5md group: version, author, creator (parjam + version) and a parjam module; the
    strings fixed-length ASCII and the version integers, as the H5MD 1.1 specification asks."""
    h5md = f.create_group("h5md")
    h5md.attrs["version"] = np.array([1, 1], dtype=np.int32)
    author = h5md.create_group("author")
    author.attrs["name"] = fixed_string(os.environ.get("USER", "parjam user"))
    creator = h5md.create_group("creator")
    creator.attrs["name"] = fixed_string("parjam")
    creator.attrs["version"] = fixed_string(__version__)
    modules = h5md.create_group("modules")
    units = modules.create_group("units")  # H5MD units module: every dimensionful dataset
    units.attrs["version"] = np.array([1, 0], dtype=np.int32)  # names its unit (file-format.md)
    units.attrs["system"] = fixed_string(UNIT_SYSTEM)
    module = modules.create_group("parjam")
    module.attrs["version"] = fixed_string(__version__)
    for key, val in (provenance or {}).items():
        val = _attr(val)
        module.attrs[key] = fixed_string(val) if isinstance(val, str) else val


def fixed_string(text):
    """A fixed-length string for an HDF5 attribute (h5py writes ``str`` as variable-length);
    non-ASCII characters become '?' (H5MD asks for the ASCII character set)."""
    return np.bytes_(str(text).encode("ascii", "replace") or b" ")


# Reduced units (H5MD units module: symbols separated by spaces, each with an optional power).
# Lengths are in units of sigma (the smallest diameter of mono- and bidisperse packings) and
# energies in units of epsilon (the prefactor of V(r)).
LENGTH, ENERGY, FORCE, TIME = "sigma", "epsilon", "epsilon sigma-1", "tau"
STIFFNESS = "epsilon sigma-2"  # V'', Hessian eigenvalues and curvatures
#: the units module's ``system``: reduced units, tau = sigma sqrt(m / epsilon), masses m = 1
UNIT_SYSTEM = "reduced: sigma epsilon tau"


def pressure_unit(d):
    return f"epsilon sigma-{d}"


OBSERVABLE_UNITS = {"pressure": "pressure", "stress_tensor": "pressure",
                    "energy_per_particle": ENERGY, "max_force": FORCE,
                    "curvature_shift": STIFFNESS, "lowest_curvature_found": STIFFNESS}


def _attr(val):
    if isinstance(val, (dict, list, tuple)) and not _is_numeric_seq(val):
        return json.dumps(val)
    if val is None:
        return "none"
    return val


def _is_numeric_seq(val):
    return isinstance(val, (list, tuple)) and all(isinstance(v, (int, float)) for v in val) and val


def provenance(comm_size, extra=None):
    """Versions, command line and PETSc options: stored with every result."""
    prov = {"versions": env.versions(), "command_line": " ".join(sys.argv),
            "ranks": int(comm_size)}
    try:
        prov["petsc_options"] = env.petsc().Options().getAll()
    except Exception:  # options database unavailable: record nothing rather than fail
        prov["petsc_options"] = {}
    prov.update(extra or {})
    return prov


def write_particles(f, pack, group="all"):
    """/particles/GROUP: box, positions (one-frame H5MD time series), diameters and species.

    The box edges are a time series too (H5MD allows a fixed box as a plain dataset, but
    MDAnalysis's reader reads ``box/edges/value`` of the frame).  Positions and their time carry
    no ``unit`` attribute: MDAnalysis refuses any unit it cannot convert to its own (even with
    convert_units=False), and parjam's units are reduced (sigma, epsilon); every other
    dimensionful quantity names its unit (docs/reference/file-format.md)."""
    part = particles_header(f, pack.d, pack.L, group)
    part["position/value"] = pack.pos[None, :, :]
    part.create_dataset("diameter", data=pack.diam).attrs["unit"] = fixed_string(LENGTH)
    species = pack.meta.get("species")
    species = np.zeros(pack.n, np.int32) if species is None else np.asarray(species, np.int32)
    part.create_dataset("species", data=species)
    return part


def particles_header(f, d, L, group="all"):
    """/particles/GROUP without its per-particle datasets: the box (attributes and the edges'
    time series) and the position time series' step and time; the caller adds
    ``position/value`` (1, N, d), ``diameter`` (N,) with :func:`diameter_attrs` and ``species``
    (N,) int32 (:func:`write_particles` at once, parjam.files.rowio by row blocks)."""
    part = f.create_group(f"particles/{group}")
    box = part.create_group("box")
    box.attrs["dimension"] = np.int32(d)
    box.attrs["boundary"] = np.array([b"periodic"] * d, dtype="S8")
    edges = box.create_group("edges")
    _time_series(edges, np.full((1, d), L), LENGTH)
    pos = part.create_group("position")
    pos.create_dataset("step", data=np.array([0], dtype=np.int64))
    pos.create_dataset("time", data=np.array([0.0]))
    return part


def diameter_attrs():
    """The attributes of /particles/GROUP/diameter."""
    return {"unit": fixed_string(LENGTH)}


def _time_series(group, value, unit):
    """An H5MD time-dependent element with one frame: step (int), time (float, tau), value."""
    group.create_dataset("step", data=np.array([0], dtype=np.int64))
    group.create_dataset("time", data=np.array([0.0])).attrs["unit"] = fixed_string(TIME)
    ds = group.create_dataset("value", data=value)
    if unit:
        ds.attrs["unit"] = fixed_string(unit)


def write_packing(path, pack, net, parameters, prov=None, observables=None):
    """One packing and its contact network (H5MD layout; see docs/reference/file-format.md); extra
    ``observables`` (name: value) go to /observables beside the network's, each an H5MD time
    series of one frame (read them back with :func:`observable`)."""
    with atomic_h5(path) as f:
        write_h5md_header(f, prov)
        part = write_particles(f, pack)
        part.create_dataset("rattler", data=net.rattler.astype(np.int8))
        _write_contacts(f, pack, net)
        write_observables(f, pack.d, dict(net.summary(), stress_tensor=net.stress,
                                          **(observables or {})))
        write_parameters(f, pack.alpha, pack.eps, pack.phi, parameters)


def write_observables(f, d, values):
    """/observables/NAME: one H5MD time series of one frame per value, with its unit."""
    obs = f.create_group("observables")
    for key, val in values.items():
        unit = OBSERVABLE_UNITS.get(key)
        unit = pressure_unit(d) if unit == "pressure" else unit
        _time_series(obs.create_group(key), np.asarray(val)[None, ...], unit)


def write_parameters(f, alpha, eps, phi, parameters):
    """/parameters attributes: alpha, epsilon, phi, then the run's ``parameters``."""
    par = f.create_group("parameters")
    par.attrs["alpha"] = alpha
    par.attrs["epsilon"] = eps
    par.attrs["phi"] = phi
    for key, val in parameters.items():
        par.attrs[key] = _attr(val)


def contact_attrs():
    """Units of the per-contact datasets of /connectivity (``contacts`` has none: its
    ``particles_group`` reference is set by :func:`link_contacts`)."""
    return {"force": {"unit": fixed_string(FORCE)},
            "stiffness": {"unit": fixed_string(STIFFNESS)}}


def link_contacts(f):
    """The H5MD connectivity module's object reference from /connectivity/contacts to the
    particles group."""
    f["connectivity/contacts"].attrs.create("particles_group", f["particles/all"].ref,
                                            dtype=h5py.ref_dtype)


def observable(f, name):
    """The value of /observables/NAME of an open packing file: the last frame of its time series
    (older parjam files held a plain dataset; both are read)."""
    obj = f["observables"][name]
    if isinstance(obj, h5py.Group):
        return obj["value"][-1]
    return obj[()]


def _write_contacts(f, pack, net):
    c = net.all_contacts
    g = f.create_group("connectivity")
    g.create_dataset("contacts", data=np.stack([c.i, c.j], axis=1).reshape(-1, 2))
    g.create_dataset("overlap", data=net.overlap)
    g.create_dataset("force", data=net.force).attrs["unit"] = fixed_string(FORCE)
    g.create_dataset("stiffness", data=net.stiffness).attrs["unit"] = fixed_string(STIFFNESS)
    link_contacts(f)  # H5MD connectivity module: an object reference to the particles group


MAX_PARTICLES = 50_000_000  # a file claiming more is refused before anything is read


def checked_dataset(f, name, path, ndims, max_size=None):
    """The h5py Dataset /name, its type and shape checked before anything is read."""
    if name not in f:
        raise ParjamError(f"{path}: missing dataset /{name}")
    obj = f[name]
    if not isinstance(obj, h5py.Dataset):
        raise ParjamError(f"{path}: /{name} is not a dataset")
    if obj.dtype.kind not in "biuf":
        raise ParjamError(f"{path}: /{name} must hold real numbers, got dtype {obj.dtype}")
    if len(obj.shape) not in ndims:
        raise ParjamError(f"{path}: /{name} has {len(obj.shape)} dimensions, expected "
                          f"{' or '.join(str(k) for k in ndims)}")
    if max_size is not None and obj.size > max_size:
        raise ParjamError(f"{path}: /{name} holds {obj.size} values: absurdly large "
                          f"(limit {max_size})")
    return obj


def _dataset(f, name, path, ndims, max_size=None):
    """A real-valued dataset as float64, its type and shape checked before it is read."""
    return np.asarray(checked_dataset(f, name, path, ndims, max_size)[()], dtype=float)


def scalar_param(params, key, default, path):
    """A finite real scalar from /parameters attributes (or the default)."""
    val = params.get(key, default)
    arr = np.asarray(val)
    if arr.size != 1 or arr.dtype.kind not in "biuf":
        raise ParjamError(f"{path}: parameter {key} must be one real number, got {val!r}")
    val = float(arr.reshape(()))
    if not np.isfinite(val):
        raise ParjamError(f"{path}: parameter {key} must be finite, got {val}")
    return val


def read_packing(path):
    """A Packing from an H5MD file (parjam's own or the reference layout), validated: every
    problem is a one-line ParjamError, never a traceback."""
    path = os.fspath(path)
    inputs.require(path)  # a FIFO, a directory, a loop: named, and never opened
    if not h5py.is_hdf5(path):
        raise ParjamError(f"{path}: not an HDF5 file")
    limit = MAX_PARTICLES * 3
    try:
        with h5py.File(path, "r") as f:
            pos = _dataset(f, "particles/all/position/value", path, (2, 3), limit)
            diam = _dataset(f, "particles/all/diameter", path, (1,), limit)
            edges = box_edges(f, path)
            species = None
            if isinstance(f.get("particles/all/species"), h5py.Dataset):
                species = _dataset(f, "particles/all/species", path, (1,), limit)
            params = dict(f["parameters"].attrs) if "parameters" in f else {}
    except (OSError, RuntimeError, KeyError) as exc:  # truncated or corrupted inside
        raise ParjamError(f"{path}: unreadable HDF5 file ({exc})") from None
    pack = validated_packing(path, pos, diam, edges, params)
    if species is not None:
        if species.shape != (pack.n,) or not np.all(species == np.round(species)):
            raise ParjamError(f"{path}: species must be {pack.n} integers")
        pack.meta["species"] = species.astype(np.int32)
    return pack


def box_edges(f, path):
    """Box edges of the last frame: an H5MD time series (``box/edges/value``, parjam's files)
    or a plain dataset (older parjam files, the reference layout, other H5MD writers)."""
    if isinstance(f.get("particles/all/box/edges"), h5py.Group):
        edges = _dataset(f, "particles/all/box/edges/value", path, (1, 2), 3 * 10**6)
        if edges.ndim == 2:
            if edges.shape[0] == 0:
                raise ParjamError(f"{path}: the box time series holds no frame")
            edges = edges[-1]
        return edges
    return np.atleast_1d(_dataset(f, "particles/all/box/edges", path, (0, 1), 3))


def validated_packing(path, pos, diam, edges, params):
    """A Packing from raw arrays (positions (N, d) or (T, N, d), diameters, box edges, the
    /parameters attributes), each problem a one-line ParjamError naming ``path``."""
    if pos.ndim == 3:
        if pos.shape[0] == 0:
            raise ParjamError(f"{path}: the position time series holds no frame")
        pos = pos[-1]
    L = check_layout(path, pos.shape, diam.shape, edges)
    message = value_problem(path, pos, diam, edges, L)
    if message:
        raise ParjamError(message)
    alpha, eps, meta = model_parameters(path, params)
    pos = wrap(pos, L)
    _check_distinct(path, pos, diam, L)
    try:
        return Packing(pos, diam, L, alpha, eps, meta)
    except ValueError as exc:
        raise ParjamError(f"{path}: {exc}") from None


def check_layout(path, pos_shape, diam_shape, edges):
    """Shapes of one frame's positions (N, d) and diameters, and the box edges; returns L."""
    if len(pos_shape) != 2 or pos_shape[1] not in (2, 3):
        raise ParjamError(f"{path}: positions must have shape (N, 2) or (N, 3), got "
                          f"{tuple(pos_shape)}")
    n, d = pos_shape
    if n < 2:
        raise ParjamError(f"{path}: a packing needs at least 2 particles, got {n}")
    if tuple(diam_shape) != (n,):
        raise ParjamError(f"{path}: diameters must have shape ({n},), got {tuple(diam_shape)}")
    if edges.shape != (d,) or not np.allclose(edges, edges[0], rtol=1e-12):
        raise ParjamError(f"{path}: box edges must be {d} equal values, got {edges}")
    if not np.all(np.isfinite(edges)):
        raise ParjamError(f"{path}: box edges contain NaN or inf")
    if edges[0] <= 0:
        raise ParjamError(f"{path}: diameters and box edges must be positive")
    return float(edges[0])


#: box edge over the smallest diameter: N = 5e7 spheres of diameter ratio 10 span ~1e5 (2D)
MAX_SPAN = 1e8


def value_problem(path, pos, diam, edges, L):
    """The first problem with (any rows of) positions and diameters, or None."""
    for name, arr in (("positions", pos), ("diameters", diam), ("box edges", edges)):
        if not np.all(np.isfinite(arr)):
            return f"{path}: {name} contain NaN or inf"
    if len(diam) == 0:
        return None
    if np.any(diam <= 0):
        return f"{path}: diameters and box edges must be positive"
    if L / diam.min() > MAX_SPAN:  # also keeps every squared distance far from overflow
        return (f"{path}: the box edge is {L / diam.min():.3g} smallest diameters: more than "
                f"{MAX_SPAN:.0e}, which no packing parjam handles spans (N <= 5e7)")
    if L <= 2.0 * diam.max() * (1.0 + 1e-9):
        return (f"{path}: box edge {L:.6g} is not larger than twice the largest "
                f"diameter {diam.max():.6g}")
    if np.abs(pos).max() > 1e3 * L:
        return (f"{path}: positions lie far outside the box of edge {L:.6g} "
                f"(largest |x| = {np.abs(pos).max():.3g})")
    return None


def model_parameters(path, params):
    """alpha, epsilon and the metadata from the /parameters attributes."""
    alpha = scalar_param(params, "alpha", 2.0, path)
    if alpha <= 1:
        raise ParjamError(f"{path}: alpha must be > 1, got {alpha}")
    eps = scalar_param(params, "epsilon", 1.0, path)
    if eps <= 0:
        raise ParjamError(f"{path}: epsilon must be > 0, got {eps}")
    meta = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in params.items()}
    meta["source"] = os.path.abspath(path)
    return alpha, eps, meta


def _check_distinct(path, pos, diam, L):
    """Duplicated particles (coinciding centres) would divide by r = 0 in every force."""
    pairs = coinciding_pairs(pos, diam, L)
    if len(pairs):
        i, j = pairs[0]
        raise ParjamError(f"{path}: particles {i} and {j} coincide ({len(pairs)} duplicated "
                          f"pair(s))")


def sha256(path):
    h = hashlib.sha256()
    with inputs.open_file(path) as fh:  # never blocks on a FIFO
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()

