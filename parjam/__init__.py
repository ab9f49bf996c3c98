"""parjam: parallel vibrational analysis of jammed soft-sphere packings.

Reproduces and extends Wyart, Silbert, Nagel & Witten, Phys. Rev. E 72, 051306 (2005).
Import the PETSc-dependent modules through :mod:`parjam.env`, which locates PETSc/SLEPc
and initialises them with the command-line options database.
"""

__version__ = "0.1.0"
