"""Every benchmark of scripts/benchmarks in its quick mode (tiny sizes), so that none rots: each
run must finish, write its JSON and its section of a page, and hold what it measured against
its peer (numpy/scipy from the same file) to a tolerance.  The memory benchmark also measures a
commit beside this tree (``--old``): a throw-away repository holding this tree's parjam, so
both columns run the same code and their outputs must be identical.  Serial pass only: the
benchmarks start their own processes."""

import json
import os
import shutil
import subprocess
import sys

import pytest

from conftest import ROOT, subprocess_env

BENCH = os.path.join(ROOT, "scripts", "bench")
sys.path.insert(0, os.path.join(ROOT, "scripts"))

from benchmarks import NAMES  # noqa: E402


def bench(tmp_path, *args):
    """scripts/bench ARGS --quick with its JSON and page in tmp_path: (rows, page text)."""
    out, page = tmp_path / "result.json", tmp_path / "page.md"
    env = subprocess_env(PARJAM_CACHE=str(tmp_path / "cache"))
    r = subprocess.run([sys.executable, BENCH, *args, "--quick", "--json", str(out), "--doc",
                        str(page)], cwd=tmp_path, env=env, capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-3000:]
    with open(out) as fh:
        result = json.load(fh)
    command = result["meta"]["command"]  # reproduces the run, without its output paths
    assert command.startswith(f"scripts/bench {args[0]} ") and "--quick" in command
    assert str(tmp_path / "result.json") not in command
    assert not [row for row in result["rows"] if row.get("error")], result["rows"]
    return result["rows"], page.read_text()


def parjam_rows(rows):
    return [r for r in rows if r.get("tree") in ("old", "new")]


@pytest.mark.serial
def test_pack_quick(tmp_path):
    rows, page = bench(tmp_path, "pack")
    (row,) = rows
    assert row["fire_steps"] > 0 and row["kernel_calls"] >= row["fire_steps"]
    assert row["max_force"] < 1e-12
    assert row["p_diff"] < 1e-10  # the file's pressure, recomputed from its positions
    assert 0 < row["kernel_s"] < row["compute_s"] and len(row["rss_mb"]) == 1
    assert "<!-- bench pack: begin -->" in page and "| variant | tree | N |" in page


@pytest.mark.serial
def test_modes_quick(tmp_path):
    rows, _ = bench(tmp_path, "modes")
    scipy_row = next(r for r in rows if r["method"] == "scipy eigsh")
    assert scipy_row["diff"] < 1e-8
    sinvert, sliced = parjam_rows(rows)
    assert sinvert["found"] == 10 and sinvert["diff"] < 1e-9 and sinvert["max_error"] < 1e-10
    assert sinvert["solves"] > 0 and sinvert["limit_s"] > sinvert["factor_s"] > 0
    assert sliced["found"] == sliced["expected"] > 0 and sliced["diff"] < 1e-9
    assert len(sinvert["rss_mb"]) == 2


@pytest.mark.serial
def test_kpm_quick(tmp_path):
    rows, _ = bench(tmp_path, "kpm")
    dense, kpm = rows
    assert dense["method"] == "dense eigvalsh" and dense["D0"] > 0
    assert kpm["matmults"] >= kpm["probes"] * kpm["moments"] // 2
    assert kpm["L1"] < 0.3 and kpm["D0_err"] < 0.2 and kpm["omega_star_err"] < 0.1


@pytest.mark.serial
def test_softmodes_quick(tmp_path):
    rows, _ = bench(tmp_path, "softmodes")
    dense = next(r for r in rows if r["variant"] == "dense SVD")
    runs = parjam_rows(rows)
    assert len(runs) == 2 and dense["count"] > dense["q"]
    for r in runs:  # Eq. 3: the count of the MUMPS inertia = the dense SVD's null space
        assert r["count"] == r["dense_count"] == dense["count"] and r["eq3"] < 1e-12
        assert r["basis_mb"] > 0


@pytest.mark.serial
def test_moduli_quick(tmp_path):
    rows, _ = bench(tmp_path, "moduli")
    direct, gamg = parjam_rows(rows)
    assert direct["diff"] < 1e-10 and gamg["diff"] < 1e-8  # against scipy's SuperLU
    assert gamg["iterations"] > direct["iterations"] >= 1
    assert abs(gamg["B"] / direct["B"] - 1) < 1e-8 and abs(gamg["G"] / direct["G"] - 1) < 1e-6


def old_repository(path):
    """A repository whose HEAD holds this tree's parjam (compiled files left out)."""
    shutil.copytree(os.path.join(ROOT, "parjam"), path / "parjam",
                    ignore=shutil.ignore_patterns("*.so", "__pycache__"))
    for cmd in (["init", "-q"], ["add", "-A"], ["-c", "user.name=bench", "-c",
                                                "user.email=bench@localhost", "commit", "-q",
                                                "-m", "old"]):
        subprocess.run(["git", *cmd], cwd=path, check=True, capture_output=True)
    return path


@pytest.mark.serial
def test_memory_quick_old_against_new(tmp_path):
    repo = old_repository(tmp_path / "repo")
    rows, page = bench(tmp_path, "memory", "--old", "HEAD", "--repo", str(repo))
    old, new = rows
    assert (old["tree"], new["tree"]) == ("old", "new") and old["n"] == new["n"] > 0
    assert new["same"] == "identical"
    for r in rows:
        assert len(r["rss_mb"]) == r["ranks"] == 2 and r["peak_mb"] > r["floor_mb"] > 0
    assert "against HEAD (`old`)" in page
    assert not os.path.exists(tmp_path / "repo" / ".git" / "worktrees" / "tree")


@pytest.mark.serial
def test_every_benchmark_is_tested_and_listed(tmp_path):
    tested = {name[len("test_"):].split("_quick")[0] for name in globals()
              if name.startswith("test_") and "_quick" in name}
    assert tested == set(NAMES)
    r = subprocess.run([sys.executable, BENCH, "list"], env=subprocess_env(),
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and all(f"  {name} " in r.stdout for name in NAMES)
