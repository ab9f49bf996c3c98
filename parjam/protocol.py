"""The settings of a packing protocol, one typed object shared by ``parjam pack`` (built from its
options) and by scenes (built from the scene's [system], [protocol] and [ensemble] tables): what
parjam.ensemble needs to make and write the states of one member.  The defaults of those
settings are defined here once; the command-line parser and the scene parser use them.
"""

import dataclasses
from dataclasses import dataclass
from typing import Optional

DEFAULT_PHI_START = {2: 0.86, 3: 0.66}  # random starts above phi_c (2D bidisperse, 3D mono)
DEFAULT_DISPERSITY = {2: "bi", 3: "mono"}  # of scenes and make_jammed (mono 2D crystallises)
DEFAULT_ALPHA = 2.0  # harmonic contacts
DEFAULT_RATIO = 1.4  # large/small diameter (bi) or max/min (poly)
DEFAULT_FTOL = 1e-13  # max |F| of a minimised state (docs/speed-accuracy.md: ftol <~ 1e-5 p)
DEFAULT_ENERGY_WINDOW = (1e-16, 2e-16)  # E/N window defining phi_c (O'Hern et al. 2003)
DEFAULT_DPHI = (1e-6, 1e-4, 1e-2)  # the ladder of parjam pack without --dphi/--pressure/--phi
LADDERS = ("compress", "decompress")
PHIC_METHODS = ("bisect", "extrapolate")


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
