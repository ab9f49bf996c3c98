"""Vibrations of a packing: the dynamical matrix of Eq. (1) as a distributed PETSc matrix
(:mod:`.hessian`), its translations (:mod:`.translations`), factorisations and inertia
(:mod:`.factor`), spectra by SLEPc shift-and-invert or slicing, or dense LAPACK for small
systems (:mod:`.spectrum`, :mod:`.dense`, chosen by :mod:`.solver_choice`), D(omega) by KPM
(:mod:`.kpm`, :mod:`.kpm_dos`), the spectra's observables (:mod:`.observables`), structure
factors (:mod:`.structure`) and elastic moduli by linear response (:mod:`.moduli`).
"""
