"""Pair potential V(r) = (eps/alpha) (1 - r/sigma_ij)^alpha for r < sigma_ij (the paper's Eq. (1)
setting: alpha = 2 harmonic, alpha = 5/2 Hertz), and its first two derivatives in r.

All functions are vectorised over contacts; ``r`` and ``sigma`` are arrays of equal shape.
"""

import numpy as np


def check_alpha(alpha):
    if not np.isfinite(alpha) or alpha <= 1.0:
        raise ValueError(f"alpha must be > 1 (got {alpha})")
    return float(alpha)


def overlap(r, sigma):
    """delta = 1 - r/sigma, the dimensionless overlap (positive in contact)."""
    return 1.0 - r / sigma


def energy(r, sigma, alpha, eps=1.0):
    d = np.maximum(overlap(r, sigma), 0.0)
    return (eps / alpha) * d**alpha


def dV(r, sigma, alpha, eps=1.0):
    """V'(r) = -(eps/sigma) delta^(alpha-1): negative for a repulsive contact."""
    d = np.maximum(overlap(r, sigma), 0.0)
    return -(eps / sigma) * d ** (alpha - 1.0)


def d2V(r, sigma, alpha, eps=1.0):
    """V''(r) = (eps/sigma^2) (alpha-1) delta^(alpha-2): the contact stiffness k."""
    d = np.maximum(overlap(r, sigma), 0.0)
    return (eps / sigma**2) * (alpha - 1.0) * d ** (alpha - 2.0)
