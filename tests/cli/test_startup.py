"""Start-up: building the command line (``parjam --help``, ``parjam COMMAND --help``, a mistyped
option) loads none of the heavy libraries; a command loads them when it runs."""

import subprocess
import sys

import pytest

from conftest import ROOT

HEAVY = ("scipy", "h5py", "mpi4py", "petsc4py", "slepc4py", "matplotlib")
COMMANDS = ("", "pack", "modes", "dos", "analyze", "moduli", "lengths", "softmodes", "run",
            "plot", "import", "export")

PROBE = """
import sys
from parjam import cli
code = cli.main(sys.argv[1:])
loaded = sorted({m.split('.')[0] for m in sys.modules} & set(%r))
print(code, ' '.join(loaded))
"""


def loaded_after(*argv):
    out = subprocess.run([sys.executable, "-c", PROBE % (HEAVY,), *argv], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    code, _, names = out.stdout.strip().splitlines()[-1].partition(" ")
    return int(code), names.split()


@pytest.mark.serial
@pytest.mark.parametrize("command", COMMANDS)
def test_help_loads_no_heavy_library(command):
    code, names = loaded_after(*([command] if command else []), "--help")
    assert code == 0
    assert names == [], f"parjam {command} --help loaded {names}"


@pytest.mark.serial
def test_a_mistyped_option_ends_before_mpi_and_petsc():
    code, names = loaded_after("pack", "--no-such-option")
    assert code == 2
    assert names == []


@pytest.mark.serial
def test_a_command_that_runs_starts_petsc(tmp_path):
    code, names = loaded_after("analyze", str(tmp_path / "missing.h5"))
    assert code == 2  # the input policy's one line, after PETSc started
    assert "petsc4py" in names and "mpi4py" in names
