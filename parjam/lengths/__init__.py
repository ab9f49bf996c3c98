"""Sound speeds and the length scales of Wyart, Silbert, Nagel & Witten, PRE 72, 051306 (2005),
Section III and its discussion: l* ~ 1/dz (cut-plane argument), l_L = c_L / omega* and
l_T = c_T / omega*, with the structure factors of the eigenmodes (parjam.vib.structure).

One module per concept, all on the distributed active network (parjam.net.active):

- :mod:`.speeds` -- rho = N'/V, c_L, c_T, the Christoffel speeds, omega* and l_L, l_T;
- :mod:`.sites` -- the network with the positions of each rank's own non-rattlers;
- :mod:`.cubes` -- one cut cube: pruning, pieces, exact soft modes by MUMPS inertia, extended
  soft modes;
- :mod:`.whole` -- one large cube counted by all the ranks together, its members where they are;
- :mod:`.lstar` -- the cubes distributed over the ranks, the table and the fitted l*;
- :mod:`.analysis` -- the whole ``parjam lengths`` analysis (its file: parjam.files.lengths).
"""

from parjam.lengths.analysis import WHAT, Lengths, compute, default_k_max, fit_structure
from parjam.lengths.cubes import CubeCount, count_cube
from parjam.lengths.lstar import LstarResult, default_e0, lstar, lstar_estimate
from parjam.lengths.speeds import (acoustic_lengths, christoffel_speeds, longitudinal_modulus,
                                   mass_density, omega_star, sound_speeds, wave_tensor)

__all__ = ["WHAT", "CubeCount", "Lengths", "LstarResult", "acoustic_lengths",
           "christoffel_speeds", "compute", "count_cube", "default_e0", "default_k_max",
           "fit_structure", "longitudinal_modulus", "lstar", "lstar_estimate", "mass_density",
           "omega_star", "sound_speeds", "wave_tensor"]
