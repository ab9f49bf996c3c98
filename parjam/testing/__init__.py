"""Test-suite helpers: pytest on every MPI rank (:mod:`.mpi_pytest`), dense references built
independently of the distributed path (:mod:`.reference`, :mod:`.softmodes_reference`),
whole-configuration gathers (:mod:`.gather`), file comparisons (:mod:`.h5compare`) and
constructed saddles (:mod:`.saddles`)."""
