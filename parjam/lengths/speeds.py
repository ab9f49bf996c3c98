"""Sound speeds, omega* and the acoustic lengths l_L = c_L / omega*, l_T = c_T / omega*
(Wyart, Silbert, Nagel & Witten, PRE 72, 051306 (2005), Section III and its discussion).

Density.  The eigenmodes (parjam.vib.spectrum) and the moduli (parjam.vib.moduli) are those of the N'
non-rattlers with unit masses; rattlers have no contacts, carry no stress and do not move with a
sound wave of the harmonic T = 0 solid.  The mass density that makes c = sqrt(modulus / rho) the
slope of the phonon branches of the dynamical matrix is therefore rho = N' m / V (m = 1), not
N / V.  With B and G the stress-strain (Wallace) moduli of parjam.vib.moduli, the long-wavelength
dispersion of a pre-stressed isotropic solid is exactly

    rho c_L^2 = B + 2 (d - 1) G / d,        rho c_T^2 = G.

For the anisotropic tensor of a finite box, the Christoffel matrix
Gamma_ik(k^) = W_ijkl k^_j k^_l / rho with W_ijkl = C_ijkl + delta_ik s_jl (Lagrangian constants
C plus the Cauchy stress s: the second derivative of the relaxed energy in the displacement
gradient) gives the speeds of each direction (:func:`christoffel_speeds`).
"""

import numpy as np

from parjam.vib import observables


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


def omega_star(spec, n_active, d, plateau=None):
    """(D0, omega*, plateau window) of a spectrum (docs/howto/spectra.md definitions)."""
    return observables.dos_summary(spec.frequency, observables.n_modes_total(n_active, d),
                                   plateau)


def acoustic_lengths(c_L, c_T, w_star):
    """l_L = c_L / omega*, l_T = c_T / omega*."""
    return c_L / w_star, c_T / w_star
