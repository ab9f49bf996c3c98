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

#: where each name lives: its module loads when the name is first used, so that importing one
#: step (the command line builds its parser from .basis and .scratch) does not load them all
WHERE = {
    **dict.fromkeys(("SoftModes", "analyze", "characterise"), "analysis"),
    **dict.fromkeys(("BASIS_METHODS", "COLUMNS_DEFAULT", "COLUMNS_MAX", "NullBasis",
                     "eq3_residual"), "basis"),
    **dict.fromkeys(("count_below", "expected_zero_modes", "gap_counts", "null_count",
                     "variational_count"), "counting"),
    **dict.fromkeys(("AXES", "CutSystem", "Plane", "WholeCut", "bound_to", "crossing",
                     "cut_masks", "cut_system", "half_edge_masks", "parse_cut", "prepare",
                     "subdivision_planes"), "cut"),
    **dict.fromkeys(("null_basis_krylov",), "krylov"),
    **dict.fromkeys(("allmax", "allreduce", "gram", "orthonormality_error", "random_block"),
                    "linalg"),
    **dict.fromkeys(("gap_above", "null_basis", "null_basis_block"), "nullspace"),
    **dict.fromkeys(("E0_LADDER", "all_localised_vectors", "coordinate_from_plane",
                     "extended_basis", "extended_fraction", "extension", "gradient_bound",
                     "localised_vectors", "modulation", "overlap_function",
                     "overlap_without_localised", "without_localised"), "observables"),
    **dict.fromkeys(("relaxed_matrix", "rigidity_matrix", "stiffness_scale",
                     "translation_columns", "translations"), "operators"),
    **dict.fromkeys(("cut_pairs", "localised_ids"), "gather"),
    **dict.fromkeys(("ScratchBasis", "ScratchSpace", "check_directory", "scratch_space"),
                    "scratch"),
    **dict.fromkeys(("energies", "omega_L2", "trial_modes"), "trial"),
}


def __getattr__(name):
    if name not in WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(f"{__name__}.{WHERE[name]}"), name)
    globals()[name] = value
    return value


def __dir__():
    return __all__


__all__ = ["ParjamError", *sorted(WHERE)]
