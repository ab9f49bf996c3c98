"""The whole ``parjam lengths`` analysis of one packing on the distributed active network
(parjam.net.active, parjam.lengths.sites): the speeds from the moduli, omega* from the spectrum, the
acoustic lengths, l* from the cut cubes and the structure factors of the eigenmodes.  Only the
parts asked for are computed; every part runs on the network's rows, no rank holds all N
positions (the eigenvectors for the structure factors come from parjam.vib.spectrum on rank 0 and
are sent to the owners of their rows)."""

from dataclasses import dataclass

import numpy as np

from parjam.vib import moduli as moduli_mod
from parjam.vib import solver_choice, spectrum, structure

from parjam.errors import ParjamError
from parjam.lengths.lstar import LstarResult, lstar
from parjam.lengths.sites import build as build_sites
from parjam.lengths.speeds import acoustic_lengths, mass_density, omega_star, sound_speeds

WHAT = ("speeds", "omega", "lstar", "structure")


@dataclass
class Lengths:
    """Everything ``parjam lengths`` computed for one packing (absent parts are None)."""

    d: int
    n: int
    n_active: int
    volume: float
    L: float
    z: float
    dz: float
    moduli: object = None  # parjam.vib.moduli.Moduli
    spectrum: object = None  # parjam.vib.spectrum.Spectrum (vectors dropped after use)
    dos: tuple = None  # (D0, omega*, plateau window)
    lstar: LstarResult = None
    structure: object = None  # parjam.vib.structure.StructureFactor
    structure_fit: dict = None

    @property
    def rho(self):
        return mass_density(self.n_active, self.volume)

    @property
    def speeds(self):
        if self.moduli is None:
            return None
        return sound_speeds(self.moduli.bulk, self.moduli.shear, self.d, self.rho)

    @property
    def omega_star(self):
        return None if self.dos is None else self.dos[1]

    @property
    def acoustic(self):
        """(l_L, l_T) when both the speeds and omega* are known."""
        if self.speeds is None or self.omega_star is None:
            return None
        return acoustic_lengths(*self.speeds, self.omega_star)

    def summary(self):
        out = {"d": self.d, "N": self.n, "N_active": self.n_active, "volume": self.volume,
               "L": self.L, "rho": self.rho, "z": self.z, "dz": self.dz}
        if self.moduli is not None:
            s = self.moduli.summary()
            out.update({"B": s["B"], "G": s["G"], "G_min": s["G_min"],
                        "c_L": self.speeds[0], "c_T": self.speeds[1]})
        if self.dos is not None:
            out.update({"D0": self.dos[0], "omega_star": self.dos[1]})
        if self.acoustic is not None:
            out.update({"l_L": self.acoustic[0], "l_T": self.acoustic[1]})
        if self.lstar is not None:
            out.update({"lstar": self.lstar.measured, "lstar_soft": self.lstar.soft_measured,
                        "lstar_extended": self.lstar.extended_measured,
                        "lstar_estimate": self.lstar.estimate})
        if self.structure_fit is not None:
            out.update({k: v for k, v in self.structure_fit.items()
                        if k not in ("peak_L", "peak_T")})
        return out


def default_k_max(mean_diameter):
    """Half the position of the first peak of S(k): pi / <sigma>."""
    return float(np.pi / mean_diameter)


def fit_structure(sf, w_star, k_fit, smooth):
    """Peaks, dispersion slopes over k <= k_fit, and l_T = 1 / k* where the transverse peak
    reaches omega* (NaN if it never does in the computed range)."""
    pL, pT = sf.peaks("L", smooth), sf.peaks("T", smooth)
    out = {"c_L_fit": structure.dispersion_slope(sf.k, pL, k_fit),
           "c_T_fit": structure.dispersion_slope(sf.k, pT, k_fit), "k_fit": float(k_fit),
           "smooth": float(smooth)}
    if w_star is not None:
        kT = structure.crossing_wavenumber(sf.k, pT, w_star)
        kL = structure.crossing_wavenumber(sf.k, pL, w_star)
        out.update({"k_star_T": kT, "l_T_structure": 1.0 / kT if kT > 0 else float("nan"),
                    "k_star_L": kL, "l_L_structure": 1.0 / kL if kL > 0 else float("nan"),
                    "l_structure_below_first_shell": bool(kT < sf.k[0])})
    return out, pL, pT


def compute(comm, source, what=("speeds", "omega"), *, matrix="full", k=None, method="auto",
            plateau=None, ells=None, samples=8, seed=0, k_max=None, k_fit=None, smooth=0.05,
            progress=None, e0=None, whole_above=None):
    """Compute only the parts in ``what`` (subset of WHAT) for one packing on ``comm``:
    ``source`` is a rowio.Rows (this rank's rows of the file), a Packing every rank holds, or
    a parjam.lengths.sites.Sites.  ``whole_above``: l* cubes of more members are counted by all
    the ranks together (parjam.lengths.lstar; default N'/P)."""
    bad = set(what) - set(WHAT)
    if bad or not what:
        raise ParjamError(f"unknown quantities {sorted(bad)}; choose from {', '.join(WHAT)}")
    log = progress or (lambda msg: None)
    mpi = comm.tompi4py()
    sites = build_sites(mpi, source)
    net = sites.net
    if net.n_active == 0 or net.excess < 0:
        raise ParjamError(
            f"packing is not jammed: {net.n_active} non-rattlers with {net.n_contacts} contacts, "
            f"{net.excess:+d} from isostatic d(N'-1)+1: no sound speeds or lengths")
    res = Lengths(net.d, net.n, net.n_active, net.volume, sites.L, net.z, net.dz)
    if "speeds" in what:
        log("speeds: elastic moduli by linear response")
        res.moduli = moduli_mod.compute(comm=comm, net=net)
    if "omega" in what or "structure" in what:
        system = spectrum.distributed_system(net)
        kk = k if k is not None else system.n_modes
        if k is None and method != "dense":  # omega* from the complete spectrum
            try:
                method = solver_choice.choose_solver(system.dof, system.n_modes, whole=True)
            except ParjamError as exc:
                raise ParjamError(
                    f"{exc}: give --k (the lowest modes; omega* then needs the plateau within "
                    "them, see --plateau) or --method dense") from None
        log(f"spectrum: {kk} lowest modes of the {matrix} matrix")
        spec = spectrum.compute(comm, system, matrix, k=kk, method=method,
                                vectors="structure" in what, progress=log)
        if spec.unstable:
            log(f"warning: {spec.n_negative} negative eigenvalues (unstable packing)")
        res.spectrum = spec
        res.dos = omega_star(spec, net.n_active, net.d, plateau)
    if "lstar" in what:
        if ells is None:
            ells = np.linspace(0.2, 1.0, 9) * sites.L
        log(f"l*: {len(ells)} cube edges x {samples} positions")
        res.lstar = lstar(comm, sites, ells, samples=samples, seed=seed, progress=log, e0=e0,
                          whole_above=whole_above)
    if "structure" in what:
        res.structure, res.structure_fit = structure_part(
            mpi, sites, res, k_max=k_max or default_k_max(sites.mean_diameter),
            k_fit=k_fit, smooth=smooth, log=log)
    return res


def owned_vectors(spec, ids):
    """The eigenvector rows of this rank's non-rattlers ``ids``: (M, len(ids), d), where
    parjam.vib.spectrum leaves them (``spec.vector_ids``)."""
    if not np.array_equal(spec.vector_ids, ids):
        raise RuntimeError("eigenvector rows do not match the owned non-rattlers")
    return spec.vectors


def structure_part(comm, sites, res, *, k_max, k_fit, smooth, log):
    """F_L, F_T summed over each rank's owned non-rattlers (their eigenvector rows, where
    parjam.vib.spectrum leaves them), one allreduce per block of wavevectors; the result is the
    same on every rank."""
    spec = res.spectrum
    k_fit = k_fit or 1.5 * 2.0 * np.pi / sites.L  # the two smallest shells, |m|^2 = 1, 2
    vec = owned_vectors(spec, sites.net.ids)
    spec.vectors = None
    log(f"structure factors: {len(spec.eigenvalue)} modes, k <= {k_max:.3g}")
    sf = structure.compute(vec, spec.frequency, sites.pos, sites.L, k_max, comm=comm)
    fit, pL, pT = fit_structure(sf, res.omega_star, k_fit, smooth)
    fit["peak_L"], fit["peak_T"] = pL, pT
    return sf, fit
