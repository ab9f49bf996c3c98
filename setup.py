"""Builds parjam's compiled kernels (parjam/pack/_kernels.c) at install time, as a plain shared
library that parjam/pack/kernels.py loads with ctypes (it is not a Python extension module; the
extension machinery only compiles and places it).  Optional: without a C compiler the install
goes on and parjam builds the library on first use or falls back to numpy, with a warning.
Everything else is in pyproject.toml."""

import hashlib
import os

from setuptools import Extension, setup

SRC = os.path.join("parjam", "pack", "_kernels.c")
SHA = hashlib.sha256(open(SRC, "rb").read()).hexdigest()

setup(ext_modules=[Extension("parjam.pack._kernels_lib", [SRC],
                             define_macros=[("PARJAM_SRC_SHA", f'"{SHA}"')],
                             extra_compile_args=["-O2", "-fno-fast-math"],
                             libraries=["m"], optional=True)])
