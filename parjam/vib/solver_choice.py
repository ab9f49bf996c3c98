"""Which solver computes which spectrum: the one policy that ``parjam modes --method auto``
(parjam.vib.spectrum.choose_method), scenes (parjam.study.plan) and ``parjam lengths`` follow.

The crossovers are the ones measured in docs/results/speed-accuracy.md (3D, 1 rank, against the dense
LAPACK truth on the same packings):

- the whole spectrum costs dof^3 by dense LAPACK: 7 s at 3000 dof, 50 s at 6100, 410 s and
  1.1 GB at 12300 ("D(omega)"), hence WHOLE_MAX_DOF; beyond it only KPM gives D(omega)
  (``parjam dos --method kpm``: 86x - 3300x cheaper than dense at 12300 dof);
- the k lowest modes: sinvert was 16x faster than dense at 3066 dof for k = 50, and from 759 dof
  on faster for k <= 10 % of the modes; a tie at <= 400 dof (SMALL_DOF); dense faster from k >=
  15 - 20 % of the modes (DENSE_FRACTION); dense reaches 1e-15 for free, so a tolerance below
  1e-12 (DENSE_TOL) picks it ("dense against sinvert");
- a window by slicing was 2x - 4.5x faster than dense from 3000 dof on, the gain growing with N
  (PARTIAL_DENSE_MAX_DOF); below that dense is a few seconds at most.
"""

from dataclasses import dataclass

from parjam.errors import ParjamError
from parjam.net.blocks import KINDS

METHODS = ("auto", "dense", "sinvert", "slice")  # parjam modes --method
MATRICES = KINDS  # the matrices of Eq. (1) a spectrum is computed for: full, relaxed, stress
#: the residual tolerances a spectrum accepts: ||D v - lambda v|| / ||D||_inf cannot go below the
#: round-off of double precision (~1e-16 per entry, summed over a row), nor mean much above 1e-2
TOL_MIN, TOL_MAX = 1e-15, 1e-2


def check_tol(tol):
    """ParjamError unless TOL_MIN <= tol < TOL_MAX."""
    if not TOL_MIN <= tol < TOL_MAX:
        raise ParjamError(f"--tol must lie in [{TOL_MIN:g}, {TOL_MAX:g}) (a residual relative to "
                          f"||D|| below ~1e-15 is round-off), got {tol:g}")

WHOLE_MAX_DOF = 12000  # the whole spectrum by dense LAPACK up to this many degrees of freedom
PARTIAL_DENSE_MAX_DOF = 3000  # the k lowest modes or a window: never dense above this
SMALL_DOF = 400  # dense at or below this whatever k (sinvert and dense tie)
DENSE_FRACTION = 0.15  # dense when k is at least this share of the modes
DENSE_TOL = 1e-12  # dense when the tolerance asked for is tighter than this
SOLVERS = ("dense", "sinvert", "slice", "slice+sinvert", "kpm")


@dataclass(frozen=True)
class Limits:
    """The policy's thresholds (a scene's [solver] table may move the first two)."""

    whole_max_dof: int = WHOLE_MAX_DOF
    partial_dense_max_dof: int = PARTIAL_DENSE_MAX_DOF
    small_dof: int = SMALL_DOF
    dense_fraction: float = DENSE_FRACTION
    dense_tol: float = DENSE_TOL


DEFAULT_LIMITS = Limits()


def choose_solver(dof, n_modes=None, *, k=None, window=None, whole=False, tol=None,
                  dos_only=False, limits=DEFAULT_LIMITS):
    """The cheapest solver (one of SOLVERS) for a spectrum of a matrix with ``dof`` degrees of
    freedom and ``n_modes`` non-translational modes: the whole spectrum (``whole``), the ``k``
    lowest modes, the modes in a frequency ``window``, or both k and a window.  ``dos_only``:
    only D(omega) is wanted, so KPM may stand in for a whole spectrum too large for dense.
    A whole spectrum beyond ``limits.whole_max_dof`` otherwise raises ParjamError."""
    if whole:
        if dof <= limits.whole_max_dof:
            return "dense"
        if dos_only:
            return "kpm"
        raise ParjamError(f"the whole spectrum of {dof} degrees of freedom is beyond dense "
                          f"LAPACK's limit of {limits.whole_max_dof}")
    if dof <= min(limits.small_dof, limits.partial_dense_max_dof):
        return "dense"
    if dof <= limits.partial_dense_max_dof:
        if window is not None or k is None or n_modes is None:
            return "dense"
        if k >= limits.dense_fraction * n_modes or (tol is not None and tol < limits.dense_tol):
            return "dense"
        return "sinvert"
    if window is not None:
        return "slice+sinvert" if k else "slice"
    return "sinvert"
