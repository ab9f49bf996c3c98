"""Sound speeds and the length scales of Wyart, Silbert, Nagel & Witten, PRE 72, 051306 (2005),
Section III and its discussion: l* ~ 1/dz (cut-plane argument), l_L = c_L / omega* and
l_T = c_T / omega*.

Density.  The eigenmodes (parjam.spectrum) and the moduli (parjam.moduli) are those of the N'
non-rattlers with unit masses; rattlers have no contacts, carry no stress and do not move with a
sound wave of the harmonic T = 0 solid.  The mass density that makes c = sqrt(modulus / rho) the
slope of the phonon branches of the dynamical matrix is therefore rho = N' m / V (m = 1), not
N / V.  With B and G the stress-strain (Wallace) moduli of parjam.moduli, the long-wavelength
dispersion of a pre-stressed isotropic solid is exactly

    rho c_L^2 = B + 2 (d - 1) G / d,        rho c_T^2 = G.

For the anisotropic tensor of a finite box, the Christoffel matrix
Gamma_ik(k^) = W_ijkl k^_j k^_l / rho with W_ijkl = C_ijkl + delta_ik s_jl (Lagrangian constants
C plus the Cauchy stress s: the second derivative of the relaxed energy in the displacement
gradient) gives the speeds of each direction (:func:`christoffel_speeds`).

l* (cut-plane counting).  Cut every contact crossing the boundary of a cube of edge l inside the
packing and keep the n non-rattlers whose centres lie in it with their Nc_in internal contacts.
Floppy modes: at least d n - Nc_in - d(d+1)/2 (Maxwell, rigid motions removed).  Every inside
particle keeps its contacts except the q cut ones, so Nc_in = (z n - q)/2 and the Maxwell count
is (q - dz n)/2 - d(d+1)/2: soft modes appear when the cut contacts outnumber the excess ones,
q > dz n.  A plane of area A is crossed by (Nc / V) <|r_a|> A contacts (r_a the component of a
contact vector along the plane normal); the cube has 2d faces of area l^(d-1) and n = rho l^d,
so q = 2d l^(d-1) (z rho / 2) <|r_a|> and

    l*_est = d z <|r_a|> / dz        (Maxwell estimate; <|r_a|> = <r>/2 in 3D, 2<r>/pi in 2D)

i.e. about 9 sigma / dz for monodisperse spheres in 3D and 16 <r> / (pi dz) in 2D.
:func:`cube_soft_modes` measures the actual number of non-trivial soft modes of cubes of edge l
at random positions: particles left with fewer than d contacts are removed iteratively (each
removal takes d - z_i trivially localised modes), the rigid motions d(d+1)/2 of every connected
piece are subtracted, and the null space of the relaxed-spring matrix of what remains is counted
exactly by MUMPS inertia (:func:`null_count`, options prefix ``lengths_inertia_``).  The
measured l* is the edge at which the mean cut-plane count of the real cubes changes sign.  Since floppy clusters along the cut
faces keep a few soft modes in cubes of any size, the soft modes are also sorted by extension
as in the paper's Appendix, inside each cube (:func:`extended_soft_count`: G multiplies
particle i by prod_a sin^2(pi u_a / l), the rigid motions removed first): ``lstar_extended``
is the edge above which no cube keeps a soft mode with e > e0 (default 0.4 x 2^-d, 40 % of a
uniform mode).

Why one file of ~600 lines: the speeds, omega* and the three lengths are one analysis (``parjam
lengths``), and l* needs its own cube counting (cut, prune, pieces, extension); its sections are
the speeds, l*, the whole analysis and the output.
"""

from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from parjam import (env, hessian, io, network, observables, softmodes, solver_choice,
                    spectrum, structure)
from parjam import moduli as moduli_mod
from parjam.errors import ParjamError
from parjam.network import analyze


# --------------------------------------------------------------------------- sound speeds

def mass_density(n_active, volume):
    """rho = N' m / V, unit masses, non-rattlers only (see the module doc)."""
    return n_active / volume


def longitudinal_modulus(B, G, d):
    """M = B + 2 (d - 1) G / d (P-wave modulus)."""
    return B + 2.0 * (d - 1) * G / d


def sound_speeds(B, G, d, rho):
    """(c_L, c_T) = (sqrt((B + 2(d-1)G/d) / rho), sqrt(G / rho)); NaN where a modulus is < 0."""
    M = longitudinal_modulus(B, G, d)
    c_L = np.sqrt(M / rho) if M >= 0 else float("nan")
    c_T = np.sqrt(G / rho) if G >= 0 else float("nan")
    return float(c_L), float(c_T)


def wave_tensor(mod):
    """W_ijkl = C_ijkl + delta_ik s_jl: second derivative of the relaxed energy density in the
    displacement gradient (Lagrangian constants C plus the pre-stress)."""
    d = mod.d
    return mod.c_lagrangian + np.einsum("ik,jl->ijkl", np.eye(d), mod.stress)


def christoffel_speeds(mod, khat, rho):
    """Sound speeds along each unit vector in ``khat`` (K, d): sqrt of the eigenvalues of
    Gamma_ik = W_ijkl k_j k_l / rho, ascending (transverse first, longitudinal last)."""
    W = wave_tensor(mod)
    G = np.einsum("ijkl,nj,nl->nik", W, khat, khat) / rho
    lam = np.linalg.eigvalsh(0.5 * (G + G.transpose(0, 2, 1)))
    return np.sqrt(np.clip(lam, 0.0, None))


# --------------------------------------------------------------------------- omega* and lengths

def omega_star(spec, n_active, d, plateau=None):
    """(D0, omega*, plateau window) of a spectrum (docs/spectra.md definitions)."""
    return observables.dos_summary(spec.frequency, observables.n_modes_total(n_active, d),
                                   plateau)


def acoustic_lengths(c_L, c_T, w_star):
    """l_L = c_L / omega*, l_T = c_T / omega*."""
    return c_L / w_star, c_T / w_star


# --------------------------------------------------------------------------- l*: cut cubes

EXTENDED_MAX_DOF = 2400  # dense null-space bases of cube cores up to this size

def mean_normal_component(rij):
    """<|r_a|> over contacts and axes: the mean bond length across a plane per unit density."""
    return float(np.abs(rij).mean())


def lstar_estimate(d, z, dz, rij):
    """Maxwell estimate l* = d z <|r_a|> / dz (module doc)."""
    return d * z * mean_normal_component(rij) / dz if dz > 0 else float("inf")


def cube_members(pos, L, x0, ell):
    """Mask of positions inside the periodic cube [x0, x0 + ell)^d."""
    return np.all(np.mod(pos - x0, L) < ell, axis=1)


def cube_network(pos, contacts, L, x0, ell):
    """Particles inside the cube (indices into pos) and the kept contacts among them (local
    indices): both ends inside, not crossing a face (parjam.softmodes.crossing)."""
    d = pos.shape[1]
    inside = cube_members(pos, L, x0, ell)
    planes = [softmodes.Plane(a, float(np.mod(x0[a], L) / L)) for a in range(d)]
    planes += [softmodes.Plane(a, float(np.mod(x0[a] + ell, L) / L)) for a in range(d)]
    cut = np.logical_or.reduce(softmodes.cut_masks(pos, contacts, L, planes))
    keep = inside[contacts.i] & inside[contacts.j] & ~cut
    idx = np.cumsum(inside) - 1
    return np.flatnonzero(inside), contacts.subset(keep), idx


def prune_underconstrained(n, d, i, j):
    """Iteratively remove particles with fewer than d contacts; returns (alive mask, number of
    trivially localised modes removed = sum of d - z_i at removal)."""
    alive = np.ones(n, dtype=bool)
    keep = np.ones(len(i), dtype=bool)
    trivial = 0
    while True:
        deg = np.bincount(i[keep], minlength=n) + np.bincount(j[keep], minlength=n)
        low = alive & (deg < d)
        if not low.any():
            return alive, trivial
        trivial += int((d - deg[low]).sum())
        alive &= ~low
        keep &= alive[i] & alive[j]


def components(n, i, j, labels=False):
    """Number of connected pieces of the contact graph (and each particle's piece)."""
    g = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n))
    count, lab = connected_components(g, directed=False)
    return (count, lab) if labels else count


@dataclass
class CubeCount:
    ell: float
    n: int  # particles inside
    q: int  # contacts of inside particles cut by the faces
    nc_in: int  # contacts kept inside
    n_core: int  # after pruning
    nc_core: int
    trivial: int  # trivially localised modes removed by pruning
    pieces: int  # connected pieces of the core
    null: int  # null space of the core's relaxed matrix (rigid motions included; -1: no gap)
    dim: int = 3
    extended: int = -1  # soft modes with extension e > e0 (-1: not computed)

    @property
    def rigid(self):
        return self.pieces * self.dim * (self.dim + 1) // 2

    @property
    def soft(self):
        """Non-trivial soft modes: null space of the core minus the rigid motions of its
        pieces (NaN when the null space had no clear gap)."""
        return self.null - self.rigid if self.null >= 0 else float("nan")

    @property
    def maxwell_core(self):
        """d n_core - Nc_core - rigid motions: a lower bound on ``soft``."""
        return self.dim * self.n_core - self.nc_core - self.rigid

    @property
    def maxwell(self):
        """The cut-plane count of the whole cube, d n - Nc_in - d(d+1)/2 = (q - dz_in n)/2 -
        d(d+1)/2: a lower bound on all its floppy modes beyond the rigid motions."""
        return self.dim * self.n - self.nc_in - self.dim * (self.dim + 1) // 2


def rigid_motions(u, d, labels):
    """Orthonormal basis (columns, d n rows) of the translations and infinitesimal rotations of
    every connected piece (``labels``) of particles at positions u."""
    cols = []
    pairs = [(0, 1)] if d == 2 else [(0, 1), (0, 2), (1, 2)]
    for p in np.unique(labels):
        m = labels == p
        r = u - u[m].mean(axis=0)
        for a in range(d):
            v = np.zeros_like(u)
            v[m, a] = 1.0
            cols.append(v.ravel())
        for a, b in pairs:
            v = np.zeros_like(u)
            v[m, a], v[m, b] = -r[m, b], r[m, a]
            cols.append(v.ravel())
    q, _ = np.linalg.qr(np.array(cols).T)
    return q


def extended_soft_count(H, u, ell, labels, e0, zero_tol=1e-8):
    """Soft modes of a cube core that are extended (Appendix of the paper, applied inside the
    cube): the null space of the dense relaxed matrix H minus the rigid motions of its pieces,
    and the eigenvalues e of G projected on it, G multiplying particle i by
    g_i^2 = prod_a sin^2(pi u_a / ell) (u measured from the cube's corner; 2^-d for a uniform
    mode): the number of e > e0.  Surface-localised floppy clusters have e ~ 0."""
    d = u.shape[1]
    top = np.abs(H).sum(axis=1).max()
    _, V = scipy.linalg.eigh(H, subset_by_value=(-np.inf, zero_tol * top))
    R = rigid_motions(u, d, labels)
    S = V - R @ (R.T @ V)
    U, sv, _ = np.linalg.svd(S, full_matrices=False)
    soft = U[:, sv > 1e-6]
    if soft.shape[1] == 0:
        return 0
    g2 = np.repeat(np.prod(np.sin(np.pi * u / ell) ** 2, axis=1), d)
    e = np.linalg.eigvalsh(soft.T @ (g2[:, None] * soft))
    return int(np.sum(e > e0))


def count_cube(pos, contacts, L, x0, ell, *, alpha, eps, scale, comm_self, e0=None,
               max_dof=EXTENDED_MAX_DOF):
    """Soft modes of one cube (see module doc), on a single-rank communicator; with ``e0`` also
    the extended ones (dense, cores of at most ``max_dof`` degrees of freedom)."""
    d = pos.shape[1]
    members, kept, idx = cube_network(pos, contacts, L, x0, ell)
    n = len(members)
    inside = np.zeros(len(pos), dtype=bool)
    inside[members] = True
    q = int(np.sum(inside[contacts.i] ^ inside[contacts.j])
               + np.sum(inside[contacts.i] & inside[contacts.j]) - len(kept))
    li, lj = idx[kept.i], idx[kept.j]
    alive, trivial = prune_underconstrained(n, d, li, lj)
    core = np.cumsum(alive) - 1
    ck = alive[li] & alive[lj]
    ci, cj = core[li[ck]], core[lj[ck]]
    n_core = int(alive.sum())
    if n_core == 0:
        return CubeCount(ell, n, q, len(kept), 0, 0, trivial, 0, 0, d)
    pieces, labels = components(n_core, ci, cj, labels=True)
    blocks = hessian.contact_blocks(kept.rij[ck], kept.r[ck], kept.sigma[ck], alpha, eps,
                                    "relaxed")
    M = hessian.assemble(comm_self, n_core, d, ci, cj, blocks, fmt="sbaij")
    try:
        null = null_count(comm_self, M, scale)
    finally:
        M.destroy()
    out = CubeCount(ell, n, q, len(kept), n_core, int(ck.sum()), trivial, int(pieces),
                    int(null), d)
    if e0 is not None and null >= 0:
        if out.soft == 0:
            out.extended = 0
        elif d * n_core <= max_dof:
            u = np.mod(pos[members][alive] - x0, L)
            H = hessian.dense_hessian(n_core, d, ci, cj, blocks)
            out.extended = extended_soft_count(H, u, ell, labels, e0)
    return out


INERTIA_PREFIX = "lengths_inertia_"  # options of the cube counts' MUMPS factorisations
GAP_THRESHOLDS = (1e-10, 1e-6)  # x stiffness scale: the zero cluster and the gap above it


def null_count(comm_self, M, scale):
    """Null-space dimension of a cube's PSD matrix M, counted by inertia (softmodes.count_below,
    under this command's own prefix) at both GAP_THRESHOLDS; -1 when the counts differ (no clear
    gap: the soft count is unknown)."""
    counts = {softmodes.count_below(comm_self, M, t * scale, prefix=INERTIA_PREFIX)
              for t in GAP_THRESHOLDS}
    return counts.pop() if len(counts) == 1 else -1


@dataclass
class LstarResult:
    ells: np.ndarray  # cube edges
    counts: list  # CubeCount per (edge, sample), edge-major
    samples: int
    estimate: float  # Maxwell estimate d z <|r_a|> / dz
    dz: float
    z: float
    failed: int = 0  # cubes whose null space had no clear gap (left out of the soft counts)
    e0: float = float("nan")  # extension threshold of the extended soft modes

    COLUMNS = ("edge", "mean n", "mean q", "mean cut-plane (Maxwell) count", "mean soft modes",
               "fraction with soft modes", "mean trivially localised", "cubes",
               "mean extended soft modes", "fraction with extended soft modes")

    def table(self):
        """One row per edge, the columns in COLUMNS (means over the cubes of that edge)."""
        rows = []
        for ell in self.ells:
            cs = [c for c in self.counts if c.ell == ell]
            if not cs:
                rows.append((ell,) + (np.nan,) * 6 + (0, np.nan, np.nan))
                continue
            known = [c.soft for c in cs if c.null >= 0]
            ext = np.array([c.extended for c in cs if c.extended >= 0])
            rows.append((ell, np.mean([c.n for c in cs]), np.mean([c.q for c in cs]),
                         np.mean([c.maxwell for c in cs]),
                         np.mean(known) if known else np.nan,
                         np.mean(np.array(known) > 0) if known else np.nan,
                         np.mean([c.trivial for c in cs]), len(cs),
                         ext.mean() if len(ext) else np.nan,
                         np.mean(ext > 0) if len(ext) else np.nan))
        return np.array(rows, dtype=float)

    @property
    def measured(self):
        """l*: the edge above which the mean cut-plane count of the real cubes is negative
        (fewer cut contacts than excess contacts inside)."""
        t = self.table()
        return crossing_down(t[:, 0], t[:, 3], 0.0)

    @property
    def extended_measured(self):
        """l* from the soft modes themselves: the edge above which no cube keeps an extended
        soft mode (e > e0), the geometric midpoint between the last edge where one does and the
        next; NaN if that is the largest edge (beyond the range) or there is none."""
        t = self.table()
        hit = np.flatnonzero(t[:, 9] > 0)
        if len(hit) == 0 or hit[-1] == len(t) - 1 or not np.isfinite(t[hit[-1] + 1, 9]):
            return float("nan")  # none, or the next edge was not measured (too large, no gap)
        return float(np.sqrt(t[hit[-1], 0] * t[hit[-1] + 1, 0]))

    @property
    def soft_measured(self):
        """The edge above which fewer than half of the cubes have non-trivial soft modes (NaN
        when surface-localised floppy clusters keep them at every edge)."""
        t = self.table()
        return crossing_down(t[:, 0], t[:, 5], 0.5)


def crossing_down(x, y, level):
    """The largest x (linear interpolation) below which y >= level: scanning down from the
    largest x, the first point with y >= level and its upper neighbour.  NaN if y >= level at the
    largest x (l* beyond the range) or nowhere (l* below it)."""
    hit = np.flatnonzero(np.asarray(y) >= level)
    if len(hit) == 0 or hit[-1] == len(y) - 1:
        return float("nan")
    b = hit[-1]
    t = (y[b] - level) / (y[b] - y[b + 1])
    return float(x[b] + t * (x[b + 1] - x[b]))


def default_e0(d):
    """Extension threshold: 40 % of a uniform mode's 2^-d (0.1 in 2D, 0.05 in 3D)."""
    return 0.4 * 2.0 ** -d


def lstar(comm, pack, ells, *, samples=8, seed=0, net=None, progress=None, e0=None,
          extended=True):
    """Cut cubes of every edge in ``ells`` at ``samples`` random positions (the same on every
    rank count: positions from ``seed``), count their soft modes; cubes are spread over the ranks
    of ``comm`` (each counted on one rank) and the counts gathered everywhere."""
    PETSc = env.petsc()
    net = net if net is not None else analyze(pack)
    if net.n_active == 0 or net.excess < 0:
        raise ParjamError(f"packing is not jammed (Nc - Nc_iso = {net.excess}): no l*")
    ells = np.asarray(sorted(float(e) for e in ells))
    if ells[0] <= 0 or ells[-1] > pack.L:
        raise ParjamError(f"cube edges must lie in (0, L = {pack.L:.4g}], got {list(ells)}")
    act = ~net.rattler
    pos = np.mod(pack.pos, pack.L)
    c = net.contacts
    scale = softmodes.stiffness_scale(c, pack.alpha, pack.eps)
    rng = np.random.default_rng(seed)
    corners = rng.uniform(0.0, pack.L, size=(len(ells), samples, pack.d))
    e0 = default_e0(pack.d) if e0 is None else e0
    mpi = comm.tompi4py()
    rank, size = mpi.Get_rank(), mpi.Get_size()
    mine = []
    # only non-rattlers take part: pass their positions and re-indexed contacts
    contacts = network.active_contacts(net)
    pos_a = pos[act]
    for t in range(len(ells) * samples):
        if t % size != rank:
            continue
        e, s = divmod(t, samples)
        mine.append((t, count_cube(pos_a, contacts, pack.L, corners[e, s], ells[e],
                                   alpha=pack.alpha, eps=pack.eps, scale=scale,
                                   comm_self=PETSc.COMM_SELF, e0=e0 if extended else None)))
    everything = sorted(sum(mpi.allgather(mine), []), key=lambda x: x[0])
    failed = sum(x[1].null < 0 for x in everything)
    if progress is not None:
        progress(f"l*: {len(everything)} cubes counted, {failed} without a clear gap")
    return LstarResult(ells, [x[1] for x in everything], samples,
                       lstar_estimate(pack.d, net.z, net.dz, c.rij), net.dz, net.z, failed,
                       e0 if extended else float("nan"))


# --------------------------------------------------------------------------- the whole analysis

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
    moduli: object = None  # parjam.moduli.Moduli
    spectrum: object = None  # parjam.spectrum.Spectrum (vectors dropped after use)
    dos: tuple = None  # (D0, omega*, plateau window)
    lstar: LstarResult = None
    structure: object = None  # parjam.structure.StructureFactor
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


def default_k_max(pack):
    """Half the position of the first peak of S(k): pi / <sigma>."""
    return float(np.pi / np.mean(pack.diam))


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


def compute(comm, pack, what=("speeds", "omega"), *, matrix="full", k=None, method="auto",
            plateau=None, ells=None, samples=8, seed=0, k_max=None, k_fit=None, smooth=0.05,
            progress=None, e0=None):
    """Compute only the parts in ``what`` (subset of WHAT) for one packing on ``comm``."""
    bad = set(what) - set(WHAT)
    if bad or not what:
        raise ParjamError(f"unknown quantities {sorted(bad)}; choose from {', '.join(WHAT)}")
    log = progress or (lambda msg: None)
    net = analyze(pack)
    if net.n_active == 0 or net.excess < 0:
        raise ParjamError(
            f"packing is not jammed: {net.n_active} non-rattlers with {net.n_contacts} contacts, "
            f"{net.excess:+d} from isostatic d(N'-1)+1: no sound speeds or lengths")
    res = Lengths(pack.d, pack.n, net.n_active, pack.volume, pack.L, net.z, net.dz)
    if "speeds" in what:
        log("speeds: elastic moduli by linear response")
        res.moduli = moduli_mod.compute(pack, comm)
    if "omega" in what or "structure" in what:
        system = spectrum.active_system(pack, net)
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
        res.dos = omega_star(spec, net.n_active, pack.d, plateau)
    if "lstar" in what:
        if ells is None:
            ells = np.linspace(0.2, 1.0, 9) * pack.L
        log(f"l*: {len(ells)} cube edges x {samples} positions")
        res.lstar = lstar(comm, pack, ells, samples=samples, seed=seed, net=net, progress=log,
                          e0=e0)
    if "structure" in what:
        res.structure, res.structure_fit = structure_part(
            comm, pack, net, res, k_max=k_max or default_k_max(pack), k_fit=k_fit,
            smooth=smooth, log=log)
    return res


def structure_part(comm, pack, net, res, *, k_max, k_fit, smooth, log):
    """F_L, F_T on rank 0 (where the eigenvectors are) and broadcast."""
    mpi = comm.tompi4py()
    spec = res.spectrum
    k_fit = k_fit or 1.5 * 2.0 * np.pi / pack.L  # the two smallest shells, |m|^2 = 1, 2
    payload, message = None, None
    if mpi.Get_rank() == 0:
        try:
            pos = np.mod(pack.pos[~net.rattler], pack.L)
            log(f"structure factors: {len(spec.eigenvalue)} modes, k <= {k_max:.3g}")
            sf = structure.compute(spec.vectors, spec.frequency, pos, pack.L, k_max)
            fit, pL, pT = fit_structure(sf, res.omega_star, k_fit, smooth)
            fit["peak_L"], fit["peak_T"] = pL, pT
            payload = (sf, fit)
        except ParjamError as exc:
            message = str(exc)
    message = mpi.bcast(message)
    if message:
        raise ParjamError(message)
    sf, fit = mpi.bcast(payload)
    spec.vectors = None
    return sf, fit


def write(path, res, prov=None):
    """/lengths/* atomically (call on one rank)."""
    with io.atomic_h5(path) as f:
        io.write_h5md_header(f, prov)
        g = f.create_group("lengths")
        g.attrs["density_convention"] = "rho = N' / V: non-rattlers, unit masses"
        for key, val in res.summary().items():
            g.attrs[key] = val
        if res.moduli is not None:
            s = g.create_group("moduli")
            s.create_dataset("stiffness", data=res.moduli.stiffness)
            s.create_dataset("stress", data=res.moduli.stress)
            s.attrs["max_residual"] = res.moduli.solver["max_residual"]
        if res.spectrum is not None:
            s = g.create_group("spectrum")
            s.create_dataset("frequency", data=res.spectrum.frequency)
            s.attrs["matrix"] = res.spectrum.matrix
            s.attrs["method"] = res.spectrum.method
            s.attrs["plateau_window"] = np.asarray(res.dos[2], float)
            s.attrs["n_negative"] = res.spectrum.n_negative
        if res.lstar is not None:
            _write_lstar(g.create_group("lstar"), res.lstar)
        if res.structure is not None:
            _write_structure(g.create_group("structure"), res.structure, res.structure_fit)


def _write_lstar(g, ls):
    g.create_dataset("edges", data=ls.ells)
    g.create_dataset("table", data=ls.table())
    g["table"].attrs["columns"] = ", ".join(ls.COLUMNS)
    cols = ("ell", "n", "q", "nc_in", "n_core", "nc_core", "trivial", "pieces", "null", "soft",
            "maxwell", "maxwell_core", "extended")
    g.create_dataset("cubes", data=np.array([[getattr(c, a) for a in cols] for c in ls.counts],
                                            dtype=float).reshape(-1, len(cols)))
    g["cubes"].attrs["columns"] = ", ".join(cols)
    for key in ("estimate", "measured", "soft_measured", "extended_measured", "samples",
                "failed", "dz", "z", "e0"):
        g.attrs[key] = getattr(ls, key)


def _write_structure(g, sf, fit):
    for name in ("omega", "k", "m2", "n_vectors", "weight_L", "weight_T"):
        g.create_dataset(name, data=getattr(sf, name))
    g.create_dataset("peak_L", data=fit["peak_L"])
    g.create_dataset("peak_T", data=fit["peak_T"])
    for key, val in fit.items():
        if key not in ("peak_L", "peak_T"):
            g.attrs[key] = val
