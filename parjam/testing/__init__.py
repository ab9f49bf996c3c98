"""Test-suite helpers: running pytest on every MPI rank."""
