"""Soft modes after plane cuts (Wyart, Silbert, Nagel & Witten, PRE 72, 051306, Sections II-III
and the Appendix): cut the contacts crossing planes, extract the null space of the rigidity
matrix, measure how extended it is, and build the anomalous trial modes.

One module per step, every step distributed over the ranks of ``comm`` (the owned active rows
[lo, hi) of parjam.net.active, one particle per block of d rows; no rank holds all N particles or
all contacts):

- :mod:`.cut` -- planes, the bonds crossing them (:func:`crossing`) and the cut system on the
  distributed active network of parjam.net.active (:func:`prepare`: each rank holds the half-edges
  of its own rows, global numbers allreduced).
- :mod:`.operators` -- M = S^T K S (Eq. 1 without the stress term) and S (Eq. 3).
- :mod:`.counting` -- the null-space dimension by MUMPS inertia, d + q - 1 - (Nc - Nc_iso).
- :mod:`.basis` -- the basis record and its Eq. 3 check; :mod:`.nullspace` -- block inverse
  iteration in column blocks (``--columns``) and the gap; :mod:`.krylov` -- SLEPc.
- :mod:`.linalg` -- distributed dense algebra on row-split column blocks.
- :mod:`.observables` -- modulation g, extension, extended subspace, f(x) (Sec. III, Appendix);
  :mod:`.trial` -- trial modes (Eq. rr) and omega_L (Eq. kkk).
- :mod:`.scratch` -- the basis out of core (``--scratch``): a row-split array on disk.
- :mod:`.analysis` -- the whole analysis; :mod:`.gather` -- the ids its file records, gathered
  on rank 0 (parjam.files.softmodes writes the file).

Dense references for tests live in :mod:`parjam.testing.softmodes_reference`.
"""

from parjam.errors import ParjamError
from parjam.softmodes.analysis import SoftModes, analyze, characterise
from parjam.softmodes.basis import (BASIS_METHODS, COLUMNS_DEFAULT, COLUMNS_MAX, NullBasis,
                                    eq3_residual)
from parjam.softmodes.counting import (count_below, expected_zero_modes, gap_counts,
                                       null_count, variational_count)
from parjam.softmodes.cut import (AXES, CutSystem, Plane, WholeCut, bound_to, crossing,
                                  cut_masks, cut_system, half_edge_masks, parse_cut, prepare,
                                  subdivision_planes)
from parjam.softmodes.krylov import null_basis_krylov
from parjam.softmodes.linalg import allmax, allreduce, gram, orthonormality_error, random_block
from parjam.softmodes.nullspace import gap_above, null_basis, null_basis_block
from parjam.softmodes.observables import (E0_LADDER, coordinate_from_plane, extended_basis,
                                          extended_fraction, extension, gradient_bound,
                                          all_localised_vectors, localised_vectors,
                                          modulation, overlap_function,
                                          overlap_without_localised, without_localised)
from parjam.softmodes.operators import (relaxed_matrix, rigidity_matrix, stiffness_scale,
                                        translation_columns, translations)
from parjam.softmodes.gather import cut_pairs, localised_ids
from parjam.softmodes.scratch import ScratchBasis, ScratchSpace, check_directory, scratch_space
from parjam.softmodes.trial import energies, omega_L2, trial_modes

__all__ = [
    "AXES", "BASIS_METHODS", "COLUMNS_DEFAULT", "COLUMNS_MAX", "CutSystem", "E0_LADDER",
    "NullBasis", "ParjamError", "Plane", "ScratchBasis", "ScratchSpace", "SoftModes",
    "WholeCut", "all_localised_vectors", "allmax", "allreduce", "analyze",
    "bound_to", "characterise", "check_directory", "coordinate_from_plane", "count_below",
    "crossing", "cut_masks", "cut_pairs", "cut_system", "energies", "eq3_residual",
    "expected_zero_modes", "extended_basis", "extended_fraction", "extension", "gap_above",
    "gap_counts",
    "gradient_bound", "gram", "half_edge_masks", "localised_ids", "localised_vectors",
    "modulation", "null_basis", "null_basis_block", "null_basis_krylov", "null_count",
    "omega_L2", "orthonormality_error", "overlap_function", "overlap_without_localised",
    "parse_cut", "prepare", "random_block", "relaxed_matrix", "rigidity_matrix",
    "scratch_space", "stiffness_scale", "subdivision_planes", "translation_columns",
    "translations", "trial_modes", "variational_count", "without_localised",
]
