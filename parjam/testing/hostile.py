"""Hostile cases of the command line, each built in its own directory and run as a user would
(a subprocess, optionally under mpirun), with the verdict the reliability rules ask for: one
``parjam: error:`` line and a non-zero status (or, for a case that must now work, status 0 and
what it must produce), no traceback, no PETSc dump, no hang, no input changed.

The cases are the third hostile round's (docs/results/hostile.md lists them with their
numbers) and the new ones found while fixing them.  tests/hostile/test_hostile_round3.py runs
every case; ``scripts/hostile_sweep.py`` runs them against any parjam (``--pythonpath`` of an
older checkout) and prints the tally.

Why one file of ~580 lines: the cases are data, one small builder each, kept together so that
the test and the sweep run exactly the same list.
"""

import contextlib
import hashlib
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field

import numpy as np

HANG_SECONDS = 40  # the limit: a case still running then is a hang
DATA = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(
    __file__)))), "tests", "data")
PACKING = "soft_d2_N64_m0.h5"  # 2D, N = 64, dphi = 1e-8 (at phi_c): the P
BIG = "soft_d2_N1024_m0.h5"  # large enough for SLEPc's shift-and-invert (modes --k 3)
DUMPS = ("Traceback", "PETSC ERROR", "MPI_ABORT", "RuntimeWarning", "Caught signal")

SCENE = """[[system]]
d = 2
N = 16
dispersity = "bi"
{system}
[protocol]
dphi = [1e-2]
[ensemble]
members = 1
seed = {seed}
[observables]
contacts = true
"""


@dataclass
class Case:
    """One hostile case: ``build(work)`` makes its files in ``work`` and returns the parjam
    arguments; ``expect`` is "error" (one line, non-zero, nothing written) or "ok" (status 0,
    then ``check(work, result)`` returns a problem or None)."""

    name: str
    group: str
    build: callable
    expect: str = "error"
    env: dict = field(default_factory=dict)
    ranks: int = 1
    check: callable = None
    needs: str = None  # "mount": a tmpfs (root)
    #: with a tmpfs: bytes left free before the first run and before its resume (the same
    #: command again); a checkpoint piece or packing file reserves its size + 1 MiB first
    room: tuple = (1536 << 10, 512 << 10)
    owner: str = "hostile"  # "clients": an importer case of parjam/files/importer.py
    new: bool = False  # found in this round, not one of the 33
    watch: tuple = ("in.h5", "P.h5")  # inputs that must not change
    timeout: float = HANG_SECONDS  # seconds: still running then is a hang
    words: tuple = ()  # the error line must say these (what the path is, ...)


def _p(work, name="P.h5", source=PACKING):
    path = os.path.join(work, name)
    shutil.copy(os.path.join(DATA, source), path)
    return path


def _scene(work, system="", seed=1, name="s.toml", head=""):
    path = os.path.join(work, name)
    with open(path, "w") as fh:
        fh.write(head + SCENE.format(system=system, seed=seed))
    return path


def _fifo(work, name):
    path = os.path.join(work, name)
    os.mkfifo(path)
    return path


def _nested(depth, open_, close):
    return open_ * depth + close * depth


# --------------------------------------------------------------------------- the builders

def _packed(work, name="in.h5"):
    """The issue's P: the phi_c state of ``parjam pack --dim 2 --n 32 --dispersity bi`` (seed
    0); its parameters are those of a ``pack --from`` run of it, so the output directory's
    parameter check does not refuse a member file that is this file."""
    made = os.path.join(work, "made")
    subprocess.run([sys.executable, "-m", "parjam", "pack", "--dim", "2", "--n", "32",
                    "--dispersity", "bi", "--dphi", "1e-2", "--out", made, "-q"],
                   check=True, capture_output=True, env=_env())
    path = os.path.join(work, name)
    shutil.copy(os.path.join(made, "member0000_phi_c.h5"), path)
    shutil.rmtree(made)
    return path


def b_member_symlink(w):
    _packed(w)
    os.makedirs(os.path.join(w, "od"))
    os.symlink("../in.h5", os.path.join(w, "od", "member0000_dphi1.0e-02.h5"))
    return ["pack", "--from", "in.h5", "--dphi", "1e-2", "--out", "od", "--no-resume", "-q"]


def b_member_hardlink(w):
    _packed(w)
    os.makedirs(os.path.join(w, "od"))
    os.link(os.path.join(w, "in.h5"), os.path.join(w, "od", "member0000_dphi1.0e-02.h5"))
    return ["pack", "--from", "in.h5", "--dphi", "1e-2", "--out", "od", "--no-resume", "-q"]


PACK16 = ["pack", "--dim", "2", "--n", "16", "--dispersity", "bi", "--dphi", "1e-2"]


def b_two_labels(w):
    return PACK16[:-1] + ["1e-2", "1.0004e-2", "--out", "od", "-q"]


def b_dry_run(w):
    return ["pack", "--n", "20000000", "--dry-run"]


def b_dos_fifos(w):
    _fifo(w, "ff"), _fifo(w, "ff2")
    return ["dos", "ff", "ff2", "--out", "o.h5"]


def b_run_fifo(w):
    _fifo(w, "ff")
    return ["run", "ff", "--dry-run"]


def b_manifest_fifo(w):
    os.makedirs(os.path.join(w, "od"))
    _fifo(w, os.path.join("od", "manifest.json"))
    return PACK16 + ["--out", "od", "-q"]


def b_petscrc_fifo(w):
    _fifo(w, ".petscrc")
    return ["info"]


def b_options_file_fifo(w):
    _fifo(w, "opts")
    return ["info", "-options_file", "opts"]


def b_scene_arrays(w):
    path = os.path.join(w, "deep.toml")
    with open(path, "w") as fh:
        fh.write(SCENE.format(system="x = " + _nested(4000, "[", "]"), seed=1))
    return ["run", path, "--dry-run"]


def b_scene_tables(w):
    path = os.path.join(w, "deep.toml")
    with open(path, "w") as fh:
        fh.write(SCENE.format(system="x = " + _nested(4000, "{a = ", "}").replace(
            "{a = }", "{a = 1}"), seed=1))
    return ["run", path, "--dry-run"]


def b_scene_seed(w):
    return ["run", _scene(w, seed=99999999999999999999999), "--out", "r", "-q"]


def b_scene_system_escape(w):
    return ["run", _scene(w, system='name = "../../ESC_SYS"'), "--out", "r", "-q"]


def _scene_named(name):
    def build(w):
        os.makedirs(os.path.join(w, "a", "b"))
        path = _scene(w, head=f'[scene]\nname = "{name}"\n')
        return ["run", path, "--dry-run"]
    return build


def _results_inside(work, result):
    """The dry run names a results directory directly under results/."""
    for line in result.stdout.splitlines():
        if line.startswith("results in "):
            out = line[len("results in "):]
            parent = os.path.dirname(os.path.normpath(out))
            return None if parent == "results" else f"results in {out}: not one directory " \
                                                     f"under results/"
    return "the dry run names no results directory"


def b_options_file_missing(w):
    return ["info", "-options_file", "/nonexistent"]


def b_options_file_garbage(w):
    with open(os.path.join(w, "garbage.opts"), "w") as fh:
        fh.write("garbage words here\n")
    return ["info", "-options_file", "garbage.opts"]


def b_options_file_self(w):
    with open(os.path.join(w, "self.opts"), "w") as fh:
        fh.write("-options_file self.opts\n")
    return ["info", "-options_file", "self.opts"]


def b_info(w):
    return ["info"]


def b_bogus_eps(w):
    _p(w, "big.h5", BIG)
    return ["modes", "big.h5", "--k", "3", "--out", "s.h5", "-q"]


def b_manifest_d_file(w):
    os.makedirs(os.path.join(w, "od"))
    with open(os.path.join(w, "od", ".manifest.d"), "w") as fh:
        fh.write("x\n")
    return PACK16 + ["--out", "od", "-q"]


def b_devfull(w):
    _p(w)
    _p(w, "Q.h5", "soft_d2_N64_m1.h5")
    return ["analyze", "--json", "P.h5", "Q.h5"]


def b_log_view(w):
    return ["info", "-log_view", ":/nonexistent/x"]


def b_log_view_input(w):
    _p(w)
    return ["analyze", "P.h5", "-log_view", ":P.h5"]


def b_window(bounds):
    def build(w):
        _p(w)
        return ["modes", "P.h5", "--window", bounds, "--out", "w.h5", "-q"]
    return build


def _no_rejected(work, result):
    if "rejected" in result.stderr or result.stderr.strip():
        return f"stderr: {result.stderr.strip()[:200]}"
    return None


def _nothing_written(work, result):
    """Refused before any work: pack wrote no member file."""
    written = [n for n in os.listdir(os.path.join(work, "od")) if n.endswith(".h5")
               and os.path.isfile(os.path.join(work, "od", n))]
    return f"written before the refusal: {written}" if written else None


def b_member_directory(w):
    os.makedirs(os.path.join(w, "od", "member0000_dphi1.0e-02.h5"))
    return PACK16 + ["--out", "od", "-q"]


def b_newline(w):
    return ["analyze", "a\nb.h5"]


def b_from_n_dim(w):
    _p(w)
    return ["pack", "--from", "P.h5", "--n", "100", "--dim", "3", "--dphi", "1e-2", "--out", "o3",
            "-q"]


def b_input_fifo(w):
    _fifo(w, "ff")
    return ["analyze", "ff"]


def b_input_directory(w):
    os.makedirs(os.path.join(w, "adir"))
    return ["analyze", "adir"]


def b_input_loop(w):
    os.symlink("loop2", os.path.join(w, "loop1"))
    os.symlink("loop1", os.path.join(w, "loop2"))
    return ["analyze", "loop1"]


def b_quench(w):
    return ["pack", "--phi", "0.70", "--ftol", "5e-4", "--n", "32", "--out", "o5", "-q"]


def b_run_stage_hardlink(w):
    scene = _scene(w)
    subprocess.run([sys.executable, "-m", "parjam", "run", scene, "--out", "r", "-q"],
                   cwd=w, env=_env(), check=True, capture_output=True)
    stages = os.path.join(w, "r", "stages")
    pack = next(d for d in sorted(os.listdir(stages)) if d.startswith("pack-"))
    member = os.path.join(stages, pack, "member0000_phi_c.h5")
    os.remove(member)
    os.link(scene, member)
    return ["run", scene, "--out", "r", "-q"]


def b_disk_full(members):
    """pack into a tmpfs of 2 MiB at ``full`` (run_case fills it to Case.room before the
    first run and before the resume)."""
    def build(w):
        return ["pack", "--dim", "2", "--n", "64", "--dispersity", "bi", "--members",
                str(members), "--dphi", "1e-4", "1e-2", "--checkpoint-every", "0.01", "--out",
                "full/o", "-q"]
    return build


# --------------------------------------------------------------------------- importer cases

def b_xyz_pbc_fff(w):
    path = os.path.join(w, "f.xyz")
    rng = np.random.default_rng(1)
    with open(path, "w") as fh:
        fh.write('20\nLattice="6 0 0 0 6 0 0 0 6" Properties=species:S:1:pos:R:3:radius:R:1 '
                 'pbc="F F F"\n')
        for x in rng.random((20, 3)) * 6:
            fh.write(f"A {x[0]} {x[1]} {x[2]} 0.5\n")
    return ["import", "f.xyz", "--out", "f.h5"]


def b_xyz_dimension7(w):
    path = os.path.join(w, "f.xyz")
    rng = np.random.default_rng(1)
    with open(path, "w") as fh:
        fh.write('20\nLattice="6 0 0 0 6 0 0 0 6" Properties=species:S:1:pos:R:3:radius:R:1 '
                 'pbc="T T T" dimension=7\n')
        for x in rng.random((20, 3)) * 6:
            fh.write(f"A {x[0]} {x[1]} {x[2]} 0.5\n")
    return ["import", "f.xyz", "--out", "f.h5"]


def _lammps(w, count, rows):
    path = os.path.join(w, "f.data")
    with open(path, "w") as fh:
        fh.write(f"LAMMPS data\n\n{count} atoms\n2 atom types\n\n0 6 xlo xhi\n0 6 ylo yhi\n"
                 f"0 6 zlo zhi\n\nAtoms\n\n")
        fh.write(rows)
    return ["import", "f.data", "--out", "f.h5"]


def b_lammps_count(count):
    def build(w):
        return _lammps(w, count, "")
    return build


def b_lammps_full_rows(w):
    rng = np.random.default_rng(2)
    rows = "".join(f"{k + 1} {k % 3 + 1} {k % 2 + 1} 0.0 {x[0]} {x[1]} {x[2]}\n"
                   for k, x in enumerate(rng.random((20, 3)) * 6))
    return _lammps(w, 20, rows)


def b_h5md_matrix(w):
    import h5py

    path = _p(w, "m.h5")
    with h5py.File(path, "r+") as f:
        edges = f["particles/all/box/edges"][()]
        del f["particles/all/box/edges"]
        f["particles/all/box/edges"] = np.diag(edges)
    return ["import", "m.h5", "--format", "h5md", "--out", "f.h5"]


# --------------------------------------------------------------------------- the list

CASES = [
    Case("member file a symlink to the --from input", "data loss", b_member_symlink),
    Case("member file a hard link to the --from input", "data loss", b_member_hardlink,
         new=True),
    Case("two --dphi values with one label", "wrong result", b_two_labels),
    Case("extxyz pbc=\"F F F\" with 3D positions", "wrong result", b_xyz_pbc_fff,
         owner="clients"),
    Case("LAMMPS bare Atoms header, full-style rows", "wrong result", b_lammps_full_rows,
         owner="clients"),
    Case("PARJAM_MEMORY_MB=nan", "wrong result", b_dry_run,
         env={"PARJAM_MEMORY_MB": "nan", "PARJAM_TIME_LIMIT": "1e12"}),
    Case("PARJAM_TIME_LIMIT=-1", "wrong result", b_dry_run, env={"PARJAM_TIME_LIMIT": "-1"},
         new=True),
    Case("dos of two FIFOs", "hang", b_dos_fifos, words=("a FIFO",)),
    Case("run of a FIFO --dry-run", "hang", b_run_fifo, words=("a FIFO",)),
    Case("a FIFO at od/manifest.json", "hang", b_manifest_fifo, words=("a FIFO",)),
    Case("a FIFO at .petscrc", "hang", b_petscrc_fifo, new=True),
    Case("-options_file a FIFO", "hang", b_options_file_fifo, new=True),
    Case("LAMMPS data with 0 atoms", "traceback", b_lammps_count(0), owner="clients"),
    Case("LAMMPS data with -3 atoms", "traceback", b_lammps_count(-3), owner="clients"),
    Case("scene arrays nested 4000 deep", "traceback", b_scene_arrays),
    Case("scene inline tables nested 4000 deep", "traceback", b_scene_tables),
    Case("scene seed = 99999999999999999999999", "traceback", b_scene_seed),
    Case("scene system named ../../ESC_SYS", "traceback", b_scene_system_escape,
         expect="ok", check=lambda w, r: None if os.listdir(os.path.join(w, "r", "stages"))
         and not os.path.exists(os.path.join(os.path.dirname(w), "ESC_SYS")) else "escaped"),
    Case("scene named /abs/dir", "traceback", _scene_named("/abs/dir"), expect="ok",
         check=_results_inside),
    Case("scene named ../../X", "traceback", _scene_named("../../X"), expect="ok",
         check=_results_inside),
    Case("scene named a/b", "traceback", _scene_named("a/b"), expect="ok",
         check=_results_inside),
    Case("-options_file /nonexistent", "traceback", b_options_file_missing),
    Case("-options_file of garbage", "traceback", b_options_file_garbage),
    Case("PETSC_OPTIONS='-options_file /nonexistent'", "traceback", b_info,
         env={"PETSC_OPTIONS": "-options_file /nonexistent"}),
    Case("PETSC_OPTIONS='-modes_eps_type bogus'", "traceback", b_bogus_eps,
         env={"PETSC_OPTIONS": "-modes_eps_type bogus"}),
    Case("-options_file that includes itself", "traceback", b_options_file_self, new=True),
    Case("a file at od/.manifest.d", "traceback", b_manifest_d_file),
    Case("analyze --json > /dev/full", "traceback", b_devfull),
    Case("-log_view :/nonexistent/x", "traceback", b_log_view),
    Case("-log_view onto the input", "data loss", b_log_view_input, new=True),
    Case("disk full on 2 ranks, then the resume", "traceback", b_disk_full(6), ranks=2,
         needs="mount", timeout=300),
    Case("disk full on 2 ranks sharing one member, then the resume", "traceback",
         b_disk_full(1), ranks=2, needs="mount", new=True, room=(512 << 10, 512 << 10)),
    Case("modes --window 0,100", "minor", b_window("0,100"), expect="ok", check=_no_rejected),
    Case("modes --window 0,1e300", "minor", b_window("0,1e300"), expect="ok",
         check=_no_rejected),
    Case("modes --window above the spectrum", "minor", b_window("10,20"), new=True),
    Case("H5MD box edges as a diagonal (D, D) matrix", "minor", b_h5md_matrix, expect="ok",
         owner="clients"),
    Case("extxyz header dimension=7", "minor", b_xyz_dimension7, owner="clients"),
    Case("a directory at a member file's name", "minor", b_member_directory,
         check=_nothing_written),
    Case("a file name with a newline", "minor", b_newline),
    Case("pack --from F --n 100 --dim 3", "minor", b_from_n_dim),
    Case("a FIFO as input", "minor", b_input_fifo, words=("a FIFO",)),
    Case("a directory as input", "minor", b_input_directory, words=("a directory",)),
    Case("a symlink loop as input", "minor", b_input_loop, words=("a symlink loop",)),
    Case("pack --phi 0.70 --ftol 5e-4 (a quench)", "minor", b_quench, expect="ok"),
    Case("run's stage file a hard link to the scene", "data loss", b_run_stage_hardlink,
         new=True, watch=("s.toml",)),
]


# --------------------------------------------------------------------------- running a case

def _env(**extra):
    env = dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
               OMPI_MCA_rmaps_base_oversubscribe="1", OMP_NUM_THREADS="1",
               OPENBLAS_NUM_THREADS="1", OMPI_MCA_mpi_yield_when_idle="1")
    for key in ("PARJAM_FAULT", "PETSC_OPTIONS", "PARJAM_MEMORY_MB", "PARJAM_TIME_LIMIT"):
        env.pop(key, None)
    env.update(extra)
    return env


@dataclass
class Outcome:
    case: Case
    verdict: str  # "pass", "FAIL: why", or "skipped: why"
    seconds: float = 0.0
    returncode: int = None
    stderr: str = ""


def _digests(work, names):
    out = {}
    for name in names:
        path = os.path.join(work, name)
        if os.path.isfile(path) and not os.path.islink(path):
            with open(path, "rb") as fh:
                out[name] = hashlib.sha256(fh.read()).hexdigest()
    return out


@contextlib.contextmanager
def _tmpfs(path, size="2m"):
    os.makedirs(path)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", path],
                       capture_output=True)
    try:
        yield r.returncode == 0
    finally:
        if r.returncode == 0:
            subprocess.run(["umount", path], check=True)


def _fill(path, leave):
    """Fill the file system of ``path`` until about ``leave`` bytes are free (hidden fillers)."""
    st = os.statvfs(path)
    free = st.f_bavail * st.f_frsize
    k = len([n for n in os.listdir(path) if n.startswith(".filler")])
    with open(os.path.join(path, f".filler{k}"), "wb") as fh:
        fh.write(b"\0" * max(free - leave, 0))


def verdict(case, result, work, before):
    """The case's verdict from a CompletedProcess."""
    err = result.stderr
    for dump in DUMPS:
        if dump in err or dump in result.stdout:
            return f"FAIL: {dump} in the output"
    if _digests(work, case.watch) != before:
        return "FAIL: an input changed"
    lines = [ln for ln in err.splitlines() if ln.strip()]
    if case.ranks > 1:  # mpirun adds its own notice of a non-zero exit
        lines = [ln for ln in lines if ln.startswith("parjam")]
    if case.expect == "error":
        if result.returncode == 0:
            return "FAIL: exit status 0"
        errors = [ln for ln in lines if ln.startswith("parjam: error:")]
        if len(errors) != 1:
            return f"FAIL: {len(errors)} error lines"
        if any(not ln.startswith("parjam: ") for ln in lines):
            return "FAIL: the message takes more than one line"
        missing = [w for w in case.words if w not in errors[0]]
        if missing:
            return f"FAIL: the message does not say {missing[0]!r}"
        problem = case.check(work, result) if case.check else None
        return f"FAIL: {problem}" if problem else "pass"
    if result.returncode != 0:
        return f"FAIL: exit status {result.returncode}: {err.strip()[-200:]}"
    problem = case.check(work, result) if case.check else None
    return f"FAIL: {problem}" if problem else "pass"


def run_case(case, work, python_path=None, mpirun=None):
    """Build and run one case in the empty directory ``work``; returns an Outcome."""
    timeout = case.timeout
    env = _env(**case.env)
    if python_path:
        env["PYTHONPATH"] = python_path
    mpirun = (mpirun or os.environ.get("PARJAM_MPIRUN", "mpirun --oversubscribe")).split()
    if case.needs == "mount" and os.geteuid() != 0:
        return Outcome(case, "skipped: needs a tmpfs mount (root)")
    with contextlib.ExitStack() as stack:
        if case.needs == "mount":
            if not stack.enter_context(_tmpfs(os.path.join(work, "full"))):
                return Outcome(case, "skipped: mount failed")
        argv = case.build(work)
        if case.needs == "mount":
            _fill(os.path.join(work, "full"), case.room[0])
        before = _digests(work, case.watch)
        cmd = [sys.executable, "-m", "parjam", *argv]
        if case.ranks > 1:
            cmd = mpirun + ["-n", str(case.ranks)] + cmd
        stdout = open("/dev/full", "w") if case.build is b_devfull else subprocess.PIPE
        t0 = time.monotonic()
        try:
            result = subprocess.run(cmd, cwd=work, env=env, stdout=stdout,
                                    stderr=subprocess.PIPE, text=True, timeout=timeout)
        except subprocess.TimeoutExpired:
            return Outcome(case, f"FAIL: hang (killed after {timeout} s)", timeout)
        finally:
            if stdout is not subprocess.PIPE:
                stdout.close()
        if result.stdout is None:
            result.stdout = ""
        seconds = time.monotonic() - t0
        outcome = verdict(case, result, work, before)
        if case.needs == "mount" and outcome == "pass":
            # the resume, with less room than one checkpoint piece's reservation
            _fill(os.path.join(work, "full"), case.room[1])
            try:
                result = subprocess.run(cmd, cwd=work, env=env, capture_output=True,
                                        text=True, timeout=timeout)
            except subprocess.TimeoutExpired:
                return Outcome(case, "FAIL: the resume hung", seconds)
            outcome = verdict(case, result, work, before)
            seconds = time.monotonic() - t0
        return Outcome(case, outcome, seconds, result.returncode, result.stderr)
