"""Elastic moduli of a jammed packing by linear response (harmonic theory at zero temperature,
periodic box; O'Hern et al., PRE 68, 011306 (2003); Lemaitre & Maloney, J. Stat. Phys. 123, 415
(2006)).  Rattlers are removed first; contacts are those among the non-rattlers.

Derivation.  Deform the box affinely, x -> (I + eps) x + u, with eps the (symmetric) linear
displacement gradient and u the non-affine displacements.  A contact's separation becomes
w = (I + eps) r + u_j - u_i (r = x_j - x_i), and the Hessian of V(|w|) with respect to w is the
contact block K = V'' n n^T + (V'/r)(I - n n^T) of Eq. (1) (parjam.vib.hessian).  Hence

    U_{eps_ab eps_cd}   = sum_c K_ac r_b r_d                          (affine, "Born")
    Xi_{ab}(j)_c        = +K_ca r_b,  Xi_{ab}(i)_c = -K_ca r_b          (U_{u eps}: force field
                                                                        of the affine strain)
    U_{uu}              = D, the full dynamical matrix of Eq. (1).

Minimising over u at fixed eps gives the relaxed second derivative per unit volume

    C^U_abcd = (1/V) [ sum K_ac r_b r_d  -  Xi_ab^T D^+ Xi_cd ]              (energy tensor)

(symmetrised over a<->b, c<->d).  D^+ acts on the complement of the d translations, to which
every Xi is orthogonal.  C^U is the second derivative of the energy in eps; with the tensile
Cauchy stress s_ab = (1/V) sum V'(r) r_a r_b / r (negative under compression, s = -p I for an
isotropic state), the Lagrangian elastic constants (strain eta = (F^T F - I)/2) are

    C_abcd = C^U_abcd - sym[delta_ac s_bd]

and the stress-strain coefficients of the pre-stressed solid (Wallace, "Thermodynamics of
crystals"), d s_ij = B_ijkl eps_kl, are

    B_ijkl = C_ijkl + (1/2)(delta_ik s_jl + delta_il s_jk + delta_jl s_ik + delta_jk s_il)
             - s_ij delta_kl.

The moduli reported are the isotropic averages of B_ijkl:

    bulk   B = (1/d^2) sum_ab B_aabb                       (= -V dp/dV for an isotropic state)
    shear  G = (1/((d-1)(d+2))) sum_abcd B_abcd P_abcd,   P = deviatoric projector,
               P_abcd = (delta_ac delta_bd + delta_ad delta_bc)/2 - delta_ab delta_cd / d

(for an isotropic tensor lambda dd + mu(dd + dd), G = mu).  The smallest shear modulus over all
directions, G_min = (1/2) lambda_min of B on the deviatoric strains (orthonormal Mandel basis),
detects packings that are unstable to some shear in the fixed box (G_min < 0).

D^+ Xi is computed with a PETSc KSP (options prefix ``moduli_``): CG on D with the translations
attached as a MatNullSpace, preconditioned through P = D + tau I, tau = 1e-10 x mean diagonal (so
the preconditioner is SPD): on one rank by a Cholesky factorisation of P (MUMPS when available),
on several by block Jacobi with an incomplete Cholesky ICC(0) of each rank's block (memory per
rank independent of the rank count; see ``response_solver``); the true relative residual
|D u - Xi| / |Xi| of every solve is reported.
"""

from dataclasses import dataclass, field

import numpy as np

from parjam import env
from parjam.net import active, potential
from parjam.vib import factor, hessian, translations
from parjam.errors import ParjamError
from parjam.logstage import log_stage


def sym_pairs(d):
    """Independent components (a, b), a <= b, of a symmetric d x d strain."""
    return [(a, b) for a in range(d) for b in range(a, d)]


def symmetrise4(T):
    """Symmetrise a 4-index tensor over a<->b and c<->d (strains are symmetric)."""
    return 0.25 * (T + T.transpose(1, 0, 2, 3) + T.transpose(0, 1, 3, 2)
                   + T.transpose(1, 0, 3, 2))


def affine_tensor(rij, blocks, volume):
    """Born term (1/V) sum K_ac r_b r_d over the given contacts, symmetrised (energy tensor,
    affine part)."""
    T = np.einsum("kac,kb,kd->abcd", blocks, rij, rij)
    return symmetrise4(T) / volume


def strain_force_fields(lo, hi, pi, pj, rij, blocks):
    """Xi_ab for every independent (a, b) on this rank's rows [lo, hi), from half-edges (pi
    owned, every contact once per end; parjam.net.active): U_{u eps} of the symmetrised strain,
    Xi_ab(j)_c = (K_ca r_b + K_cb r_a)/2 on the j end of a contact, minus that on the i end, so
    the owned end i of a half-edge with r = x_j - x_i gets -(K_ca r_b + K_cb r_a)/2."""
    d = rij.shape[1]
    out = []
    for a, b in sym_pairs(d):
        f = 0.5 * (blocks[:, :, a] * rij[:, b:b + 1] + blocks[:, :, b] * rij[:, a:a + 1])
        xi = np.zeros((hi - lo, d))
        for c in range(d):
            xi[:, c] = -np.bincount(pi - lo, weights=f[:, c], minlength=hi - lo)
        out.append(xi)
    return out


def half_sum(comm, local):
    """The sum over contacts of a per-half-edge sum (each contact counted twice, once per end):
    half the allreduced value."""
    return 0.5 * comm.tompi4py().allreduce(local)


def tensile_stress(rij, r, sigma, alpha, eps, volume):
    """Cauchy stress s_ab = (1/V) sum V'(r) r_a r_b / r of the contacts (negative = compressive)."""
    w = potential.dV(r, sigma, alpha, eps) / r
    return np.einsum("k,ka,kb->ab", w, rij, rij) / volume


def lagrangian_tensor(c_energy, s):
    """C_abcd = C^U_abcd - sym[delta_ac s_bd]."""
    d = s.shape[0]
    return c_energy - symmetrise4(np.einsum("ac,bd->abcd", np.eye(d), s))


def stress_strain_tensor(c_lagr, s):
    """Wallace's B_ijkl = C_ijkl + (d_ik s_jl + d_il s_jk + d_jl s_ik + d_jk s_il)/2 - s_ij d_kl."""
    e = np.eye(s.shape[0])
    extra = 0.5 * (np.einsum("ik,jl->ijkl", e, s) + np.einsum("il,jk->ijkl", e, s)
                   + np.einsum("jl,ik->ijkl", e, s) + np.einsum("jk,il->ijkl", e, s))
    return c_lagr + extra - np.einsum("ij,kl->ijkl", s, e)


def mandel(T):
    """The symmetric-strain tensor T as a d(d+1)/2 square matrix in an orthonormal basis."""
    d = T.shape[0]
    basis = []
    for a, b in sym_pairs(d):
        E = np.zeros((d, d))
        E[a, b] = E[b, a] = 1.0 if a == b else 1.0 / np.sqrt(2.0)
        basis.append(E)
    return np.array([[np.einsum("ij,ijkl,kl->", Ei, T, Ej) for Ej in basis] for Ei in basis])


def bulk_modulus(Bt):
    d = Bt.shape[0]
    return float(np.einsum("aabb->", Bt) / d**2)


def deviatoric_projector(d):
    e = np.eye(d)
    return (0.5 * (np.einsum("ac,bd->abcd", e, e) + np.einsum("ad,bc->abcd", e, e))
            - np.einsum("ab,cd->abcd", e, e) / d)


def shear_modulus(Bt):
    """Isotropic average of the shear moduli (deviatoric projection)."""
    d = Bt.shape[0]
    return float(np.einsum("abcd,abcd->", Bt, deviatoric_projector(d)) / ((d - 1) * (d + 2)))


def softest_shear(Bt):
    """Smallest shear modulus over all directions and its strain (unit Frobenius norm): half the
    smallest eigenvalue of the symmetric part of B on the deviatoric strains (Mandel basis)."""
    d = Bt.shape[0]
    w, v = np.linalg.eigh(mandel(deviatoric_projector(d)))
    dev = v[:, w > 0.5]  # orthonormal basis of the deviatoric subspace
    M = mandel(Bt)
    lam, vec = np.linalg.eigh(dev.T @ (0.5 * (M + M.T)) @ dev)
    x = dev @ vec[:, 0]
    E = np.zeros((d, d))
    for k, (a, b) in enumerate(sym_pairs(d)):
        E[a, b] = E[b, a] = x[k] if a == b else x[k] / np.sqrt(2.0)
    return float(0.5 * lam[0]), E


def min_shear_modulus(Bt):
    return softest_shear(Bt)[0]


@dataclass
class Moduli:
    """Linear-response elastic constants of one packing (all tensors d x d x d x d)."""

    d: int
    n_active: int
    n_contacts: int
    volume: float
    pressure: float
    stress: np.ndarray  # tensile Cauchy stress of the contact network
    c_affine: np.ndarray  # Born term of the energy tensor
    c_energy: np.ndarray  # C^U: relaxed energy second derivative in eps, per volume
    c_lagrangian: np.ndarray
    stiffness: np.ndarray  # Wallace B_ijkl (stress-strain coefficients)
    solver: dict = field(default_factory=dict)

    @property
    def bulk(self):
        return bulk_modulus(self.stiffness)

    @property
    def shear(self):
        return shear_modulus(self.stiffness)

    @property
    def shear_min(self):
        return min_shear_modulus(self.stiffness)

    @property
    def bulk_affine(self):
        return bulk_modulus(stress_strain_tensor(lagrangian_tensor(self.c_affine, self.stress),
                                                 self.stress))

    @property
    def shear_affine(self):
        return shear_modulus(stress_strain_tensor(lagrangian_tensor(self.c_affine, self.stress),
                                                  self.stress))

    def summary(self):
        B, G = self.bulk, self.shear
        return {"N_active": self.n_active, "Nc": self.n_contacts, "pressure": self.pressure,
                "B": B, "G": G, "G_over_B": G / B, "G_min": self.shear_min,
                "B_affine": self.bulk_affine, "G_affine": self.shear_affine,
                "max_residual": self.solver.get("max_residual"),
                "iterations": self.solver.get("iterations")}


@dataclass
class ResponseSystem:
    """This rank's share of the non-rattler network (parjam.net.active): rows [lo, hi) of the N'
    re-indexed non-rattlers, the half-edges pi (owned) -> pj and their blocks K of Eq. (1)."""

    n: int
    d: int
    rows: tuple
    n_contacts: int
    pi: np.ndarray
    pj: np.ndarray
    rij: np.ndarray
    r: np.ndarray
    sigma: np.ndarray
    blocks: np.ndarray


def response_system(net):
    """From a distributed active network; raises ParjamError for an unjammed packing."""
    if net.n_active == 0 or net.excess < 0:
        raise ParjamError(
            f"packing is not jammed: {net.n_active} non-rattlers with {net.n_contacts} "
            f"contacts, {net.excess:+d} from isostatic d(N'-1)+1: no elastic moduli")
    c = net.contacts
    return ResponseSystem(net.n_active, net.d, net.rows, net.n_contacts, c.i, c.j, c.rij, c.r,
                          c.sigma, net.blocks("full"))


def active_network(pack, comm=None):
    """The response system of a packing every rank holds (tests, small systems)."""
    comm = comm or env.petsc().COMM_WORLD
    return response_system(active.from_packing(comm, pack))


MAX_IT = {False: 1000, True: 10000}  # CG iteration cap: factorisation / block Jacobi


def response_solver(comm, D, P, distributed=None):
    """KSP: CG on D (options prefix ``moduli_``), preconditioned through P: on one rank
    (``distributed`` False; default: the size of ``comm`` is 1) by a Cholesky factorisation of P
    (MUMPS when available); on several by block Jacobi, one block per rank (PCASM without
    overlap), each an incomplete Cholesky ICC(0) of the rank's diagonal block of P (sub-solver
    prefix ``moduli_sub_``).  Block Jacobi keeps no coarse operators and no factor fill, so its
    memory per rank does not grow with the rank count at a fixed number of particles per rank
    (docs/results/benchmarks.md); its iterations grow with the rank count (one block
    per rank), hence the larger cap.  Options (-moduli_pc_type gamg, -moduli_sub_pc_type ...)
    override both choices."""
    PETSc = env.petsc()
    distributed = comm.getSize() > 1 if distributed is None else distributed
    ksp = PETSc.KSP().create(comm=comm)
    ksp.setOptionsPrefix("moduli_")
    ksp.setOperators(D, P)
    ksp.setType("cg")
    ksp.setNormType(PETSc.KSP.NormType.UNPRECONDITIONED)
    ksp.setTolerances(rtol=1e-11, atol=0.0, max_it=MAX_IT[distributed])
    pc = ksp.getPC()
    if distributed:
        # block Jacobi as additive Schwarz without overlap (the same operator; petsc4py 3.18
        # reaches the blocks' solvers only through PCASM), "basic" so that CG keeps a symmetric
        # preconditioner also if the user asks for an overlap (-moduli_pc_asm_overlap)
        pc.setType("asm")
        pc.setASMOverlap(0)
        pc.setASMType(PETSc.PC.ASMType.BASIC)
    else:
        factor.use_cholesky(pc)
    ksp.setFromOptions()
    if pc.getType() == "asm":
        incomplete_cholesky_blocks(ksp)
    return ksp


def incomplete_cholesky_blocks(ksp):
    """ICC(0) on every block of an additive-Schwarz ``ksp`` (set up here) unless the user chose
    the blocks' PC (-moduli_sub_pc_type, read, never written): PETSc's default for AIJ blocks,
    ILU(0), is not symmetric in floating point and has no positive-definite shift, which CG
    needs.  ICC shifts its pivots positive (MAT_SHIFT_POSITIVE_DEFINITE, PETSc's default)."""
    PETSc = env.petsc()
    ksp.setUp()
    if PETSc.Options(ksp.getOptionsPrefix() + "sub_").hasName("pc_type"):
        return
    for sub in ksp.getPC().getASMSubKSP():
        sub.getPC().setType("icc")
        sub.getPC().setFromOptions()  # -moduli_sub_pc_factor_* still apply


def solve_responses(comm, D, rhs, d, tau_rel=1e-10, distributed=None):
    """u = D^+ Xi for every Xi in ``rhs`` (this rank's rows, (n_loc, d)); returns the matrix
    of dot products Xi_k . u_l, and the solver report.  Raises ParjamError when a solve does not
    converge (zero modes of D beyond the translations, or a solver failure).  ``distributed``:
    the preconditioner of ``response_solver``."""
    ns, tvecs = translations.nullspace(D, d)
    D.setNullSpace(ns)
    diag = D.getDiagonal()
    tau = tau_rel * diag.sum() / diag.getSize()
    P = D.duplicate(copy=True)
    P.shift(tau)
    P.setNearNullSpace(ns)
    ksp = response_solver(comm, D, P, distributed)
    xis, us, report = [], [], {"iterations": [], "residuals": [], "tau": float(tau),
                               "ksp_type": ksp.getType(), "pc_type": ksp.getPC().getType(),
                               "rtol": ksp.getTolerances()[0]}
    r = D.createVecLeft()
    for xi in rhs:
        b = D.createVecLeft()
        b.array[:] = xi.ravel()
        ns.remove(b)  # exact zero in exact arithmetic: only round-off
        u = D.createVecRight()
        ksp.solve(b, u)
        D.mult(u, r)
        r.axpy(-1.0, b)
        rel = r.norm() / b.norm() if b.norm() > 0 else 0.0
        report["iterations"].append(ksp.getIterationNumber())
        report["residuals"].append(float(rel))
        xis.append(b)
        us.append(u)
    Q = np.array([[xi.dot(u) for u in us] for xi in xis])
    translations.destroy(xis, us, tvecs, r, diag, ksp, P, ns)
    report["max_residual"] = max(report["residuals"])
    bad = 1e3 * report["rtol"] + 1e-10
    if report["max_residual"] > bad:
        raise ParjamError(
            f"linear response did not converge (relative residual {report['max_residual']:.1e}, "
            f"tolerance {bad:.0e}): the dynamical matrix has zero modes beyond the {d} "
            "translations (an unstable or partly floppy packing) or the solver failed")
    return Q, report


def dynamical_matrix(comm, rs):
    """Distributed full dynamical matrix of the non-rattlers (Eq. (1)), AIJ for CG/GAMG."""
    return hessian.assemble(comm, rs.n, rs.d, rs.pi, rs.pj, rs.blocks, rows=rs.rows, fmt="aij")


def energy_tensor(c_affine, Q, d, volume):
    """C^U = C_affine - (1/V) Xi^T D^+ Xi, filled over symmetric index pairs."""
    pairs = sym_pairs(d)
    NA = np.zeros((d, d, d, d))
    for k, (a, b) in enumerate(pairs):
        for m, (c, e) in enumerate(pairs):
            q = 0.5 * (Q[k, m] + Q[m, k])
            for i, j in ((a, b), (b, a)):
                for p, s in ((c, e), (e, c)):
                    NA[i, j, p, s] = q
    return c_affine - NA / volume


def compute(pack=None, comm=None, progress=None, net=None, distributed=None):
    """Linear-response elastic constants on communicator ``comm`` (PETSc) of a distributed
    active network ``net`` (parjam.net.active), or of a packing every rank holds; ``distributed``
    chooses the preconditioner (``response_solver``; default: by the size of ``comm``)."""
    PETSc = env.petsc()
    comm = comm or PETSc.COMM_WORLD
    net = net if net is not None else active.from_packing(comm, pack)
    rs = response_system(net)
    V, d = net.volume, net.d
    s = half_sum(comm, tensile_stress(rs.rij, rs.r, rs.sigma, net.alpha, net.eps, V))
    c_aff = half_sum(comm, affine_tensor(rs.rij, rs.blocks, V))
    with log_stage("moduli: assemble"):
        D = dynamical_matrix(comm, rs)
        rhs = strain_force_fields(*rs.rows, rs.pi, rs.pj, rs.rij, rs.blocks)
    if progress is not None:
        progress(f"N' = {rs.n}, Nc = {rs.n_contacts}: {len(rhs)} linear-response solves")
    try:
        with log_stage("moduli: solve"):
            Q, report = solve_responses(comm, D, rhs, d, distributed=distributed)
    finally:
        D.destroy()
    c_u = energy_tensor(c_aff, Q, d, V)
    c_l = lagrangian_tensor(c_u, s)
    return Moduli(d, rs.n, rs.n_contacts, V, float(-np.trace(s) / d), s, c_aff, c_u, c_l,
                  stress_strain_tensor(c_l, s), report)
