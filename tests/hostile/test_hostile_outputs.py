"""Hostile outputs (parjam.files.outputs, docs/explanation/reliability.md "Outputs"): every command that writes,
given an output that would destroy something or cannot be written, ends with one line
``parjam: error: ...`` and a non-zero status *before any work*, and leaves every input, device
and directory as it was.  A full disk during the write is one line, no partial file, no crash at
exit (a tiny tmpfs where mount works, i.e. as root; a simulated ENOSPC everywhere).

In-process (``parjam.cli.main``) on both passes, each rank in its own tmp_path (the checks are
collective: rank 0 looks, every rank raises); subprocess checks (exit status, the crash at exit,
mpirun -n 2) in the serial pass only.
"""

import contextlib
import errno
import hashlib
import io
import os
import shutil
import stat
import subprocess
import sys

import pytest

from parjam import cli
from parjam.files import outputs
from conftest import DATA

PACKING = os.path.join(DATA, "soft_d2_N64_m0.h5")  # 2D, N = 64, dphi = 1e-8

SCENE = """[[system]]
d = 2
N = 16
dispersity = "bi"
[protocol]
dphi = [1e-2]
[ensemble]
members = 1
seed = 1
[observables]
contacts = true
"""


def run_cli(argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = cli.main([str(a) for a in argv])
    return rc, out.getvalue(), err.getvalue()


def assert_one_line(rc, err):
    from mpi4py import MPI

    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert rc != 0, err
    assert "Traceback" not in err, err
    if MPI.COMM_WORLD.Get_rank() == 0 or lines:
        assert len(lines) == 1 and lines[0].startswith("parjam: error: "), err


def digest(path):
    with open(path, "rb") as fh:
        return hashlib.sha256(fh.read()).hexdigest()


def snapshot(root):
    """Every entry under ``root``: kind and, for files, contents (device nodes are not read)."""
    out = {}
    for base, dirs, files in os.walk(root):
        for name in dirs + files:
            path = os.path.join(base, name)
            st = os.lstat(path)
            kind = stat.S_IFMT(st.st_mode)
            out[os.path.relpath(path, root)] = (kind, digest(path) if stat.S_ISREG(st.st_mode)
                                                else None)
    return out


# --- the commands that write, each as (argv, its inputs) for an output path -------------------
def file_commands(tmp):
    """command -> (function of the hostile path giving argv, the input that must survive)."""
    pack, spec, spec2 = tmp["packing"], tmp["spectrum"], tmp["spectrum2"]
    ok = os.path.join(tmp["root"], "fine")
    return {
        "modes --out": (lambda o: ["modes", pack, "--k", "3", "--out", o, "-q"], pack),
        "modes --plot": (lambda o: ["modes", pack, "--k", "3", "--out", ok + ".h5", "--plot", o,
                                    "-q"], pack),
        "dos --out": (lambda o: ["dos", spec, spec2, "--out", o], spec),
        "dos --plot": (lambda o: ["dos", spec, spec2, "--out", ok + ".h5", "--plot", o], spec),
        "moduli --out": (lambda o: ["moduli", pack, "--out", o, "-q"], pack),
        "lengths --out": (lambda o: ["lengths", pack, "--what", "speeds", "--out", o, "-q"], pack),
        "softmodes --out": (lambda o: ["softmodes", pack, "--cut", "x=0.5", "--out", o, "-q"],
                            pack),
        "export --out": (lambda o: ["export", pack, "--out", o], pack),
        "plot --out": (lambda o: ["plot", spec, "--out", o, "-q"], spec),
        "plot --json": (lambda o: ["plot", spec, "--img", ok, "--json", o, "-q"], spec),
    }


def dir_commands(tmp):
    scene = tmp["scene"]
    return {
        "pack --out": (lambda o: ["pack", "--dim", "2", "--n", "16", "--dispersity", "bi",
                                  "--dphi", "1e-2", "--out", o, "-q"], tmp["packing"]),
        "run --out": (lambda o: ["run", scene, "--out", o, "-q"], scene),
        "plot --img": (lambda o: ["plot", tmp["spectrum"], "--img", o, "-q"], tmp["spectrum"]),
    }


@pytest.fixture(scope="module")
def made(shared_tmp):
    """A packing, two spectra of different packings and a scene, made once (rank 0 writes)."""
    import pathlib

    root = pathlib.Path(shared_tmp) / "outputs-src"
    pack = str(root / "p.h5")
    specs = []
    for k, src in enumerate((PACKING, os.path.join(DATA, "soft_d2_N64_m1.h5"))):
        path = str(root / f"s{k}.h5")
        rc, _, err = run_cli(["modes", src, "--k", "6", "--out", path, "-q"])
        assert rc == 0, err
        specs.append(path)
    from mpi4py import MPI

    scene = root / "scene.toml"
    if MPI.COMM_WORLD.Get_rank() == 0:
        shutil.copy(PACKING, pack)
        scene.write_text(SCENE)
    MPI.COMM_WORLD.Barrier()
    return {"packing": pack, "spectrum": specs[0], "spectrum2": specs[1], "scene": str(scene)}


@pytest.fixture
def tmp(made, tmp_path):
    """Copies of the inputs in this test's own directory."""
    out = {"root": str(tmp_path)}
    for key, src in made.items():
        dst = str(tmp_path / os.path.basename(src))
        shutil.copy(src, dst)
        out[key] = dst
    return out


@pytest.fixture
def no_work(monkeypatch):
    """Any reading of a packing or spectrum, any pack member or scene stage is work: forbidden
    (the output checks must come first)."""
    from parjam.files import h5md as pio, modes_io
    from parjam.study import members
    from parjam.study.runner import Runner

    def forbidden(*a, **k):
        raise AssertionError("work started before the outputs were checked")

    monkeypatch.setattr(pio, "read_packing", forbidden)
    monkeypatch.setattr(modes_io, "read_spectrum", forbidden)
    monkeypatch.setattr(members, "pack_member", forbidden)
    monkeypatch.setattr(Runner, "run", forbidden)


def make_device(path):
    """A character device like /dev/null (1, 3) made here with mknod, or a FIFO when this user
    may not make devices; returns what was made."""
    try:
        os.mknod(path, 0o666 | stat.S_IFCHR, os.makedev(1, 3))
        return "device"
    except PermissionError:
        os.mkfifo(path)
        return "fifo"


@contextlib.contextmanager
def readonly_dir(path):
    """A directory no one may write in: chmod for a user; for root (who ignores permissions) a
    read-only tmpfs mounted on it, if mount works here."""
    os.makedirs(path)
    if os.geteuid() != 0:
        os.chmod(path, 0o555)
        try:
            yield path
        finally:
            os.chmod(path, 0o755)
            os.rmdir(path)
        return
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=16k", "tmpfs", path],
                       capture_output=True)
    if r.returncode != 0:
        pytest.skip("root without mount: no directory root cannot write in")
    try:
        yield path
    finally:
        subprocess.run(["umount", path], check=True)
        os.rmdir(path)


@contextlib.contextmanager
def full_disk(path, size="16k", fill=True):
    """A tiny tmpfs on ``path`` (root with mount), filled to the last byte by a hidden filler
    file (``fill``; else it fills while the command writes), else None (the caller simulates
    ENOSPC).  Yields the directory to write in."""
    os.makedirs(path)
    ok = os.geteuid() == 0 and subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", path],
        capture_output=True).returncode == 0
    try:
        if ok and fill:
            fd = os.open(os.path.join(path, ".filler"), os.O_WRONLY | os.O_CREAT)
            with contextlib.suppress(OSError):
                while os.write(fd, b"\0" * 512):
                    pass
            os.close(fd)
        if ok:
            os.makedirs(os.path.join(path, "out"))
        yield os.path.join(path, "out") if ok else None
    finally:
        if ok:
            subprocess.run(["umount", path], check=True)
        os.rmdir(path)


FILE_TARGETS = ("input", "symlink", "hardlink", "dotdot", "device", "fifo", "directory",
                "below_file", "readonly", "readonly_missing_dir", "same_as_other_output")


def hostile_file_target(kind, tmp, inp, stack):
    """The hostile output path of one kind, or None when it does not apply."""
    root = tmp["root"]
    if kind == "input":
        return inp
    if kind == "symlink":
        link = os.path.join(root, "link.h5")
        os.symlink(inp, link)
        return link
    if kind == "hardlink":
        link = os.path.join(root, "hard.h5")
        os.link(inp, link)
        return link
    if kind == "dotdot":
        os.makedirs(os.path.join(root, "sub"), exist_ok=True)
        return os.path.join(root, "sub", "..", os.path.basename(inp))
    if kind == "device":
        path = os.path.join(root, "dev0")
        make_device(path)
        return path
    if kind == "directory":
        return root
    if kind == "fifo":
        path = os.path.join(root, "dev0")
        os.mkfifo(path)
        return path
    if kind == "readonly_missing_dir":
        ro = stack.enter_context(readonly_dir(os.path.join(root, "ro")))
        return os.path.join(ro, "nodir", "x.png")
    if kind == "below_file":
        return os.path.join(tmp["scene"], "x.png")
    if kind == "readonly":
        return os.path.join(stack.enter_context(readonly_dir(os.path.join(root, "ro"))), "x.png")
    if kind == "same_as_other_output":
        return os.path.join(root, "fine.h5")
    raise AssertionError(kind)


@pytest.mark.parametrize("kind", FILE_TARGETS)
def test_file_outputs_refused_before_any_work(tmp, no_work, kind):
    """Every file output of every command, for every hostile kind: one line, before any work,
    nothing changed (inputs byte for byte, a device still a device, no new file).  (``plot
    --out`` onto an .h5 input is refused for its name already: still one line.)"""
    tried = 0
    for name, (argv, inp) in file_commands(tmp).items():
        if kind == "same_as_other_output" and "--plot" not in name:
            continue
        with contextlib.ExitStack() as stack:
            target = hostile_file_target(kind, tmp, inp, stack)
            before = snapshot(tmp["root"])
            rc, _, err = run_cli(argv(target))
            assert_one_line(rc, err)
            assert snapshot(tmp["root"]) == before, f"{name}: something changed"
        for extra in ("link.h5", "hard.h5", "dev0"):
            with contextlib.suppress(FileNotFoundError):
                os.remove(os.path.join(tmp["root"], extra))
        tried += 1
    assert tried >= 2


DIR_TARGETS = ("input", "regular_file", "device", "below_file", "readonly")


@pytest.mark.parametrize("kind", DIR_TARGETS)
def test_directory_outputs_refused_before_any_work(tmp, no_work, kind):
    for name, (argv, inp) in dir_commands(tmp).items():
        with contextlib.ExitStack() as stack:
            root = tmp["root"]
            if kind == "input":
                target = inp
            elif kind == "regular_file":
                target = tmp["packing"]
            elif kind == "device":
                target = os.path.join(root, "dev0")
                make_device(target)
            elif kind == "below_file":
                target = os.path.join(tmp["scene"], "out")
            else:
                target = os.path.join(stack.enter_context(
                    readonly_dir(os.path.join(root, "ro"))), "out")
            before = snapshot(root)
            rc, _, err = run_cli(argv(target))
            assert_one_line(rc, err)
            assert snapshot(root) == before, f"{name}: something changed"
        with contextlib.suppress(FileNotFoundError):
            os.remove(os.path.join(tmp["root"], "dev0"))


def test_missing_directories_are_made_at_the_write(tmp):
    """``--out spectra/NAME`` (README) and ``--plot nodir/x.png``: made, not a traceback."""
    out = os.path.join(tmp["root"], "a", "b", "s.h5")
    png = os.path.join(tmp["root"], "nodir", "x.png")
    rc, _, err = run_cli(["modes", tmp["packing"], "--k", "3", "--out", out, "--plot", png,
                          "-q"])
    assert rc == 0, err
    from mpi4py import MPI

    if MPI.COMM_WORLD.Get_rank() == 0:
        assert os.path.isfile(out)
        with open(png, "rb") as fh:
            assert fh.read(8) == b"\x89PNG\r\n\x1a\n"


def test_symlink_to_a_fresh_name_writes_the_target_and_keeps_the_link(tmp):
    """A link to a file that is not an input is followed: the file is replaced, the link stays."""
    victim = os.path.join(tmp["root"], "old.xyz")
    with open(victim, "w") as fh:
        fh.write("old\n")
    link = os.path.join(tmp["root"], "link.xyz")
    os.symlink(victim, link)
    rc, _, err = run_cli(["export", tmp["packing"], "--out", link])
    assert rc == 0, err
    from mpi4py import MPI

    if MPI.COMM_WORLD.Get_rank() != 0:
        return  # only rank 0 writes (into its own directory)
    assert os.path.islink(link) and os.path.realpath(link) == os.path.realpath(victim)
    with open(victim) as fh:
        assert int(fh.readline()) == 64  # the XYZ header: N particles


# --- a full disk ------------------------------------------------------------------------------
def writing_commands(tmp, out_dir):
    pack, spec, spec2 = tmp["packing"], tmp["spectrum"], tmp["spectrum2"]
    o = lambda name: os.path.join(out_dir, name)  # noqa: E731
    return {
        "modes": ["modes", pack, "--k", "3", "--vectors", "--out", o("s.h5"), "-q"],
        "dos": ["dos", spec, spec2, "--out", o("d.h5")],
        "moduli": ["moduli", pack, "--out", o("m.h5"), "-q"],
        "lengths": ["lengths", pack, "--what", "speeds", "--out", o("l.h5"), "-q"],
        "softmodes": ["softmodes", pack, "--cut", "x=0.5", "--vectors", "--out", o("x.h5"),
                      "-q"],
        "export": ["export", pack, "--out", o("p.xyz")],
        "plot": ["plot", spec, "--out", o("s.png"), "-q"],
        "pack": ["pack", "--dim", "2", "--n", "16", "--dispersity", "bi", "--dphi", "1e-2",
                 "--out", o("packs"), "-q"],
    }


def test_disk_full_is_one_line_and_leaves_no_partial_file(tmp):
    """A full tmpfs (root): one line each, no file left on it (pack's directory may be made:
    directories take no blocks, its manifest fails)."""
    with full_disk(os.path.join(tmp["root"], "full")) as full:
        if full is None:
            pytest.skip("no tmpfs mount here (not root): see the simulated ENOSPC test")
        for name, argv in writing_commands(tmp, full).items():
            rc, _, err = run_cli(argv)
            assert_one_line(rc, err)
            assert "No space left on device" in err or not err.strip(), (name, err)
            left = [os.path.join(b, f) for b, _, fs in os.walk(full) for f in fs]
            assert not left, (name, left)


def test_simulated_enospc_at_fsync(tmp, monkeypatch):
    """Where mount is not possible: the disk fills at fsync (delayed allocation): one line, no
    file, no temporary left, for every command that writes."""
    real = os.fsync

    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    out_dir = os.path.join(tmp["root"], "out")
    os.makedirs(out_dir)
    for name, argv in writing_commands(tmp, out_dir).items():
        monkeypatch.setattr(os, "fsync", full)
        try:
            rc, _, err = run_cli(argv)
        finally:
            monkeypatch.setattr(os, "fsync", real)
        assert_one_line(rc, err)
        left = [os.path.join(b, f) for b, _, fs in os.walk(out_dir) for f in fs]
        assert not left, (name, left)
        shutil.rmtree(out_dir)
        os.makedirs(out_dir)


# --- subprocess: real exit status, no crash at exit (serial pass only) -----------------------
def _env():
    from conftest import subprocess_env

    return subprocess_env()


@pytest.mark.serial
@pytest.mark.parametrize("ranks", [1, 2])
@pytest.mark.parametrize("command", ["modes", "moduli", "pack", "pack-shared"])
def test_disk_full_exit_without_crash(tmp_path, command, ranks):
    """The crash at exit seen before (PETSc caught a SEGV in HDF5's cleanup, exit 59) is gone:
    exit 2 and one line on every rank, 1 and 2 ranks (pack-shared: one member shared by the
    ranks, whose group's rank 0 meets the full disk in the middle of the run)."""
    if os.geteuid() != 0:
        pytest.skip("needs a tmpfs mount (root)")
    pack = str(tmp_path / "p.h5")
    shutil.copy(PACKING, pack)
    argv = {"modes": ["modes", pack, "--k", "3", "--out", "{full}/s.h5", "-q"],
            "moduli": ["moduli", pack, "--out", "{full}/m.h5", "-q"],
            "pack": ["pack", "--dim", "2", "--n", "16", "--dispersity", "bi", "--members", "2",
                     "--dphi", "1e-2", "--out", "{full}/o", "-q"],
            "pack-shared": ["pack", "--dim", "2", "--n", "16", "--dispersity", "bi",
                            "--members", "1", "--dphi", "1e-2", "--out", "{full}/o", "-q"]
            }[command]
    # pack-shared: 16 KiB free, so the manifest is written and the first packing file is not
    with full_disk(str(tmp_path / "full"), fill=command != "pack-shared") as full:
        if full is None:
            pytest.skip("mount failed")
        argv = [a.format(full=full) for a in argv]
        pre = [] if ranks == 1 else ["mpirun", "--oversubscribe", "-n", str(ranks)]
        r = subprocess.run(pre + [sys.executable, "-m", "parjam"] + argv, cwd=tmp_path,
                           env=_env(), capture_output=True, text=True, timeout=300)
        left = [f for _, _, fs in os.walk(full) for f in fs if f != "manifest.json"]
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    if ranks > 1:  # mpirun adds its own notice of a non-zero exit (not parjam's output)
        lines = [ln for ln in lines if ln.startswith("parjam")]
    assert len(lines) == 1 and "No space left on device" in lines[0], r.stderr
    for crash in ("PETSC ERROR", "MPI_ABORT", "Traceback", "signal"):
        assert crash not in r.stderr, r.stderr
    assert not left, left


# --- the policy module itself -----------------------------------------------------------------
def test_problems_names_each_case(tmp_path):
    inp = tmp_path / "in.h5"
    inp.write_bytes(b"x")
    (tmp_path / "d").mkdir()
    os.symlink(inp, tmp_path / "l.h5")
    os.mkfifo(tmp_path / "fifo")
    cases = {
        str(inp): "is the input",
        str(tmp_path / "l.h5"): "is the input",
        str(tmp_path / "d"): "is a directory",
        str(tmp_path / "fifo"): "a FIFO",
        str(inp / "x.h5"): "not a directory",
    }
    for path, words in cases.items():
        found = outputs.problems(files=[("--out", path)], inputs=[str(inp)])
        assert found and words in found[0], (path, found)
    for fine in ("new.h5", "nodir/deeper/new.h5"):  # missing directories are made at the write
        assert outputs.problems(files=[("--out", str(tmp_path / fine))], inputs=[str(inp)]) == []
    assert outputs.problems(files=[("--out", str(tmp_path / "a.h5")),
                                   ("--plot", str(tmp_path / "a.h5"))])


def test_atomic_h5_is_complete_or_absent(tmp_path):
    import h5py
    import numpy as np

    path = tmp_path / "a.h5"
    with outputs.atomic_h5(path) as f:
        f["x"] = np.arange(5.0)
    with h5py.File(path, "r") as f:
        assert list(f["x"][()]) == [0, 1, 2, 3, 4]
    with pytest.raises(ZeroDivisionError):
        with outputs.atomic_h5(path) as f:
            f["y"] = np.ones(3)
            1 / 0
    with h5py.File(path, "r") as f:  # the old file, untouched
        assert "y" not in f
    assert sorted(os.listdir(tmp_path)) == ["a.h5"]


def test_json_text_has_no_nan():
    import json

    import numpy as np

    text = outputs.json_text({"a": np.float64("nan"), "b": [np.inf, 1.5], "c": np.int64(3)})
    assert json.loads(text) == {"a": None, "b": [None, 1.5], "c": 3}
