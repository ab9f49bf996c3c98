"""The settings of a packing protocol, one typed object shared by ``parjam pack`` (built from its
options) and by scenes (built from the scene's [system], [protocol] and [ensemble] tables): what
parjam.pack.ensemble needs to make and write the states of one member.  The defaults of those
settings are defined here once; the command-line parser and the scene parser use them.
"""

import dataclasses
from dataclasses import dataclass
from typing import Optional

from parjam.errors import ParjamError

DEFAULT_PHI_START = {2: 0.86, 3: 0.66}  # random starts above phi_c (2D bidisperse, 3D mono)
DEFAULT_DISPERSITY = {2: "bi", 3: "mono"}  # of scenes and make_jammed (mono 2D crystallises)
DEFAULT_ALPHA = 2.0  # harmonic contacts
DISPERSITIES = ("mono", "bi", "poly")  # --dispersity (the diameters: parjam.pack.randomstart)
DEFAULT_RATIO = 1.4  # large/small diameter (bi) or max/min (poly)
DEFAULT_FTOL = 1e-13  # max |F| of a minimised state (docs/results/speed-accuracy.md: ftol <~ 1e-5 p)
DEFAULT_ENERGY_WINDOW = (1e-16, 2e-16)  # E/N window defining phi_c (O'Hern et al. 2003)
DEFAULT_DPHI = (1e-6, 1e-4, 1e-2)  # the ladder of parjam pack without --dphi/--pressure/--phi
LADDERS = ("compress", "decompress")
PHIC_METHODS = ("bisect", "extrapolate")


OVERLAP_MIN = 1e-12  # overlaps below ~1e4 ulps of 1 - r/sigma cannot be told from gaps
OVERLAP_MAX = 1e-3  # a "phi_c" state with larger overlaps is not near jamming
WINDOW_MIN_RATIO = 1.05  # HIGH/LOW: a narrower window is hit only by luck


def check_tolerances(ftol, energy_window, alpha, d, names=("--ftol", "--energy-window"),
                     bisection=True):
    """Refuse an --energy-window or --ftol that cannot define a jammed state, with the reason.

    A state with E/N = LOW has overlaps delta ~ (alpha LOW / d)^(1/alpha) (d contacts per
    particle, V = delta^alpha / alpha), contact forces ~ delta^(alpha-1) and stiffnesses
    (alpha-1) delta^(alpha-2) (eps, sigma units).  Its contacts are defined only if delta is far
    above the round-off of 1 - r/sigma, and its force balance only if --ftol is small against
    its contact forces yet above the forces' round-off (~1e-16 x stiffness).  ``names`` are
    the option (or scene key) names the messages use.  Without the ``bisection`` (a quench at
    a fixed phi) no state of the window is made: only the round-off floor of --ftol applies,
    at the overlaps of the random start."""
    if not bisection:
        floor = 1e-16 * (alpha - 1.0) * 0.05 ** (alpha - 2.0) if alpha >= 2 else 0.0
        if ftol < floor:
            raise ParjamError(f"{names[0]} {ftol:g} is below the round-off level of the forces "
                              f"(~{floor:.1e} = 1e-16 x the largest contact stiffness): no "
                              f"minimisation reaches it")
        return
    lo, hi = energy_window
    delta = (alpha * lo / d) ** (1.0 / alpha)
    delta_hi = (alpha * hi / d) ** (1.0 / alpha)
    force = delta ** (alpha - 1.0)
    # the stiffest contacts met on the way: at E/N = LOW, or at the overlaps ~0.05 of the
    # random start's first minimum (alpha > 2 stiffens with the overlap)
    # (alpha < 2 softens with the overlap: its forces' round-off is relative, not checked)
    floor = 1e-16 * (alpha - 1.0) * max(delta, 0.05) ** (alpha - 2.0) if alpha >= 2 else 0.0
    if delta < OVERLAP_MIN:
        raise ParjamError(f"{names[1]} LOW = {lo:g} means overlaps ~{delta:.1e}, within "
                          f"round-off of 1 - r/sigma (needs >= {OVERLAP_MIN:g}): contacts "
                          f"cannot be told from gaps there; use LOW >= "
                          f"{d * OVERLAP_MIN ** alpha / alpha:.1e}")
    if delta_hi > OVERLAP_MAX:
        raise ParjamError(f"{names[1]} HIGH = {hi:g} means overlaps ~{delta_hi:.1e}: that "
                          f"state is not near jamming; use HIGH <= "
                          f"{d * OVERLAP_MAX ** alpha / alpha:.1e}")
    if hi < WINDOW_MIN_RATIO * lo:
        raise ParjamError(f"{names[1]} {lo:g} {hi:g} is too narrow (HIGH/LOW < "
                          f"{WINDOW_MIN_RATIO}): the bisection would land in it only by luck")
    if ftol > 1e-2 * force:
        raise ParjamError(f"{names[0]} {ftol:g} is not small against the contact forces "
                          f"(~{force:.1e}) "
                          f"of a state with E/N = {lo:g}: force balance cannot define its "
                          f"contacts; use {names[0]} <= {1e-2 * force:.1e} or a higher {names[1]}")
    if ftol < floor:
        raise ParjamError(f"{names[0]} {ftol:g} is below the round-off level of the forces "
                          f"(~{floor:.1e} = 1e-16 x the largest contact stiffness): no "
                          f"minimisation reaches it")


@dataclass(frozen=True)
class PackingProtocol:
    """One ensemble's packing protocol: the system (dim, n, alpha, dispersity, ratio), the
    ensemble (seed, members), the states (exactly one of ``phi``, ``dphi``, ``pressure``), the
    phi_c search and tolerances, and where and how the files are written.  Validation of user
    input stays with the command or scene parser that builds it (one-line errors naming their
    own options or keys)."""

    dim: int
    n: int
    out: str
    alpha: float = DEFAULT_ALPHA
    dispersity: str = "mono"
    ratio: float = DEFAULT_RATIO
    seed: int = 0
    members: int = 1
    phi: Optional[float] = None  # a single quench at this phi (no phi_c search)
    dphi: Optional[tuple] = None  # phi - phi_c of the ladder's states
    pressure: Optional[tuple] = None  # target pressures
    ladder: str = "compress"
    phic_method: str = "bisect"
    phi_start: Optional[float] = None  # None: DEFAULT_PHI_START[dim]
    ftol: float = DEFAULT_FTOL
    energy_window: tuple = DEFAULT_ENERGY_WINDOW
    no_phic_file: bool = False
    resume: bool = True  # parjam pack --no-resume: recompute members and drop checkpoints
    checkpoint_every: float = 0.0  # seconds between a member's checkpoints (0: none)
    start: Optional[str] = None  # pack --from FILE: start from this packing, not at random
    start_sha256: Optional[str] = None  # of that file (the manifest keys a resumed run by it)

    def __post_init__(self):
        if self.phi_start is None:
            object.__setattr__(self, "phi_start", DEFAULT_PHI_START[self.dim])
        for name in ("dphi", "pressure", "energy_window"):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, tuple(float(x) for x in value))

    @classmethod
    def from_namespace(cls, ns):
        """The protocol of parsed ``parjam pack`` options (after their validation)."""
        return cls(**{f.name: getattr(ns, f.name) for f in dataclasses.fields(cls)
                      if hasattr(ns, f.name)})
