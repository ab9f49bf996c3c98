"""README.md's command blocks run as written, in order, in one directory (serial pass only: they
start their own processes).  Blocks that install software (``./scripts/quickstart``,
``./ci/test``, ``module load``) are left out: CI runs them itself.

Documented substitutions, to keep the run short (about a minute on 2 cores):

| README | here |
|---|---|
| ``--n 1024`` | ``--n 32`` |
| ``--members 8`` | ``--members 2`` |
| ``--k 50`` | ``--k 20`` |
| ``scenes/paper-3d.toml`` | the same scene with N = 32, 2 members and 3 states |
"""

import os
import re
import subprocess
import sys

import pytest
from conftest import ROOT, subprocess_env

SUBSTITUTIONS = [("--n 1024", "--n 32"), ("--members 8", "--members 2"), ("--k 50", "--k 20"),
                 ("scenes/paper-3d.toml", "paper-3d-small.toml")]
SKIP = ("./scripts/quickstart", "./ci/test", "module load")


def readme_blocks():
    text = open(os.path.join(ROOT, "README.md")).read()
    blocks = re.findall(r"```sh\n(.*?)```", text, flags=re.S)
    return [b for b in blocks if not any(s in b for s in SKIP)]


def small_scene(path):
    text = open(os.path.join(ROOT, "scenes", "paper-3d.toml")).read()
    for old, new in (("N = 1024", "N = 32"), ("members = 6", "members = 2"),
                     ("dphi = [1e-8, 1e-6, 1e-5, 1e-4, 1e-3, 1e-2, 1e-1]",
                      "dphi = [1e-4, 1e-2, 1e-1]"),
                     ('at = [1e-8]', 'at = [1e-4]'),
                     ('at = ["phi_c", 1e-4, 1e-2]', 'at = [1e-4, 1e-2]')):
        assert old in text, old  # the substitution still applies to the bundled scene
        text = text.replace(old, new)
    with open(path, "w") as fh:
        fh.write(text)


def test_readme_has_command_blocks():
    blocks = readme_blocks()
    assert len(blocks) >= 5
    assert any("parjam import" in b for b in blocks) and any("parjam dos" in b for b in blocks)


@pytest.mark.serial
def test_readme_commands_run_as_written(tmp_path):
    small_scene(tmp_path / "paper-3d-small.toml")
    script = "\n".join(readme_blocks())
    for old, new in SUBSTITUTIONS:
        assert old in script, old
        script = script.replace(old, new)
    env = subprocess_env(PATH=os.path.dirname(sys.executable) + os.pathsep + os.environ["PATH"])
    r = subprocess.run(["bash", "-euo", "pipefail", "-x", "-c", script], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-4000:]
    for made in ("packings/member0001_dphi1.0e-01.h5", "p2d/member0000_p1.0e-03.h5", "m0.xyz",
                 "spec.full.h5", "spec.relaxed.h5", "win.h5", "dos.h5", "dos.png", "soft.h5",
                 "moduli.h5", "len.h5", "spectra.png", "fx.png", "m0.h5",
                 "from-m0/member0000_dphi1.0e-02.h5", "results/paper-3d", "figs"):
        assert os.path.exists(tmp_path / made), made
    assert "Traceback" not in r.stderr and "warning: -" not in r.stderr
