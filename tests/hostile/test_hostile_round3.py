"""The third hostile round (docs/results/hostile.md): every case of parjam.testing.hostile run
as a user would (a subprocess, under mpirun for the 2-rank ones), serial pass only; and, on
both passes, the policies behind the fixes checked directly: the input policy
(parjam.files.inputs), the tree check of directory outputs (parjam.files.outputs), PETSc's
start-up checks (parjam.options), the machine limits (parjam.resources), the scene's names and
bounds, pack's labels and --from flags, the window cut at the spectrum's edge (against a dense
reference), and groups of ranks that end together (parjam.ranks.GroupFailures).

The importer cases of parjam.testing.hostile (owner "clients") are left to the importer's own
tests: they are not run here.
"""

import os

import numpy as np
import pytest

from parjam import options, resources
from parjam.errors import ParjamError
from parjam.files import inputs, manifest, outputs, petscfiles
from parjam.testing import hostile
from conftest import DATA

from test_hostile_outputs import assert_one_line, run_cli

OURS = [c for c in hostile.CASES if c.owner == "hostile"]


@pytest.mark.serial
@pytest.mark.parametrize("case", OURS, ids=[c.name for c in OURS])
def test_case(tmp_path, case):
    """One line and a non-zero status (or status 0 and its result), no traceback, no dump, no
    hang, no input changed."""
    out = hostile.run_case(case, str(tmp_path))
    if out.verdict.startswith("skipped"):
        pytest.skip(out.verdict)
    assert out.verdict == "pass", f"{out.verdict}\n{out.stderr}"


def test_the_cases_cover_the_issue():
    """The issue's 33 cases are 36 commands here (its three scene names and its two nestings
    are one case each there), 6 of them the importer's; then the new ones."""
    issue = [c for c in hostile.CASES if not c.new]
    assert len(issue) == 36
    assert len([c for c in issue if c.owner == "clients"]) == 6
    assert len({c.name for c in hostile.CASES}) == len(hostile.CASES)


# --------------------------------------------------------------------------- the input policy

def test_input_kinds_are_named(tmp_path):
    (tmp_path / "f").write_bytes(b"x")
    (tmp_path / "d").mkdir()
    os.mkfifo(tmp_path / "fifo")
    os.symlink("l2", tmp_path / "l1")
    os.symlink("l1", tmp_path / "l2")
    os.symlink("gone", tmp_path / "dangling")
    cases = {"f": None, "d": "a directory", "fifo": "a FIFO", "l1": "a symlink loop",
             "dangling": "a dangling symlink to gone", "missing": "missing",
             "f/below": "below a file that is not a directory"}
    for name, kind in cases.items():
        assert inputs.kind(str(tmp_path / name)) == kind, name
    assert inputs.kind("/dev/null") == "a character device"
    assert "reading it would block" in inputs.problem(str(tmp_path / "fifo"))
    assert inputs.problem(str(tmp_path / "d"), directory_ok=True) is None
    assert inputs.problem(str(tmp_path / "missing")).endswith(": no such file")


def test_open_file_never_blocks_on_a_fifo(tmp_path):
    """The FIFO is refused by its kind, before open(2) (which would block: no writer)."""
    os.mkfifo(tmp_path / "fifo")
    with pytest.raises(ParjamError, match="a FIFO"):
        inputs.open_file(str(tmp_path / "fifo"))
    with pytest.raises(ParjamError, match="a FIFO"):
        from parjam.files.h5md import sha256

        sha256(str(tmp_path / "fifo"))
    (tmp_path / "f").write_text("abc")
    with inputs.open_file(str(tmp_path / "f"), "r") as fh:
        assert fh.read() == "abc"


@pytest.mark.parametrize("text,safe", [("../../X", "___.._X"), ("/abs/dir", "_abs_dir"),
                                       ("a/b", "a_b"), ("ok-name_1.5", "ok-name_1.5"),
                                       (".hidden", "_hidden"), ("-opt", "_opt"),
                                       ("tab\there\n", "tab_here_")])
def test_names_from_user_text_are_one_component(tmp_path, text, safe):
    got = inputs.component(text)
    assert got == safe and os.sep not in got and got not in (".", "..")
    assert os.path.dirname(inputs.inside(str(tmp_path), got)) == str(tmp_path)


def test_unusable_and_colliding_names_are_refused(tmp_path):
    for bad in ("", "..", "/", "x" * 101):
        with pytest.raises(ParjamError):
            inputs.component(bad)
    with pytest.raises(ParjamError, match="same file name"):
        inputs.distinct({"a/b": "a_b", "a_b": "a_b"})
    with pytest.raises(ParjamError, match="same file name"):
        inputs.distinct({"Big": "Big", "big": "big"})  # a case-insensitive file system
    with pytest.raises(ParjamError, match="outside"):
        inputs.inside(str(tmp_path), "..", "x")
    assert inputs.shown("a\nb") == "a\\nb"


def test_tree_check_names_each_foreign_entry(tmp_path):
    """What pack writes in --out: a link, a FIFO, a wrong kind, a hard link to the input."""
    inp = tmp_path / "in.h5"
    inp.write_bytes(b"x")
    od = tmp_path / "od"

    def found(make):
        if od.exists():
            import shutil

            shutil.rmtree(od)
        od.mkdir()
        make()
        return outputs.tree_problems("--out", str(od), manifest.owned, [str(inp)])

    assert found(lambda: os.symlink(inp, od / "member0000_phi_c.h5"))[0].count("is a symlink")
    assert "is a FIFO" in found(lambda: os.mkfifo(od / "manifest.json"))[0]
    assert "where parjam keeps a directory" in found(
        lambda: (od / ".manifest.d").write_text("x"))[0]
    assert "is a directory" in found(lambda: (od / "member0000_dphi1.0e-02.h5").mkdir())[0]
    assert "is the input" in found(lambda: os.link(inp, od / "member0003_phi_c.h5"))[0]
    assert "is a FIFO" in found(lambda: ((od / ".checkpoint" / "member0000.d").mkdir(
        parents=True), os.mkfifo(od / ".checkpoint" / "member0000.d" / "pending.g1.h5")))[0]
    # a user's own files beside parjam's are not parjam's business
    assert found(lambda: (os.symlink(inp, od / "notes.h5"), os.mkfifo(od / "pipe"))) == []


# --------------------------------------------------------------------------- PETSc's start

def test_options_files_are_followed_and_cycles_refused(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "a.opts").write_text("# comment\n-options_file b.opts\n-modes_eps_nev 3\n")
    (tmp_path / "b.opts").write_text("-log_view :here.txt # trailing comment\n")
    files, tokens = petscfiles.options_files(["-options_file", "a.opts"])
    assert files == ["a.opts", "b.opts"] and ("log_view", ":here.txt") in options.pairs(tokens)
    assert options.destinations(tokens) == [("-log_view", "here.txt")]
    (tmp_path / "b.opts").write_text("-options_file a.opts\n")
    with pytest.raises(ParjamError, match="includes itself"):
        petscfiles.options_files(["-options_file", "a.opts"])
    os.mkfifo(tmp_path / "fifo.opts")
    with pytest.raises(ParjamError, match="a FIFO"):
        petscfiles.options_files(["-options_file", "fifo.opts"])


def test_startup_problems(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("PETSC_OPTIONS", raising=False)
    assert petscfiles.startup_problem(["-log_view", ":/nonexistent/x"]).startswith(
        "-log_view /nonexistent/x: /nonexistent is not a directory")
    assert petscfiles.startup_problem(["-log_view", "ascii:ok.txt:ascii_info_detail"]) is None
    assert petscfiles.startup_problem(["-modes_eps_view", "draw:host:0"]) is None  # a display
    assert "no such file" in petscfiles.startup_problem(["-options_file", "/nonexistent"])
    monkeypatch.setenv("PETSC_OPTIONS", "-options_file /nonexistent -modes_eps_type bogus")
    assert "no such file" in petscfiles.startup_problem([])
    assert options.all_user_args(["-x"]) == ["-x", "-options_file", "/nonexistent",
                                             "-modes_eps_type", "bogus"]
    monkeypatch.delenv("PETSC_OPTIONS")
    os.mkfifo(tmp_path / ".petscrc")
    assert "a FIFO" in petscfiles.startup_problem([])
    assert petscfiles.startup_problem(["-skip_petscrc"]) is None


def test_the_dump_of_a_failed_start_becomes_one_line():
    from parjam import env

    dump = ("[0]PETSC ERROR: --------------------- Error Message ----------\n"
            "[0]PETSC ERROR: Invalid argument\n"
            "[0]PETSC ERROR: Unknown first token in options file g.opts line 1: garbage\n"
            "[0]PETSC ERROR: See https://petsc.org/release/faq/ for trouble shooting.\n"
            "[0]PETSC ERROR: #1 PetscOptionsInsertFilePetsc() at options.c:526\n")
    assert env.startup_message(dump, None) == ("Unknown first token in options file g.opts "
                                                "line 1: garbage (invalid argument)")


# --------------------------------------------------------------------------- limits and scenes

@pytest.mark.parametrize("text", ["nan", "inf", "-inf", "0", "-1", "x"])
def test_machine_limits_must_be_finite_and_positive(text):
    with pytest.raises(ParjamError):
        resources.positive_setting("PARJAM_MEMORY_MB", text, "a number of megabytes")
    assert resources.positive_setting("PARJAM_MEMORY_MB", "1e3", "MB") == 1000.0


SCENE = hostile.SCENE


def test_scene_integers_fit_64_bits_and_nesting_is_bounded():
    from parjam.study import scene

    with pytest.raises(ParjamError, match=r"seed: must lie in \[0, 9223372036854775807\]"):
        scene.loads(SCENE.format(system="", seed=2**63))
    assert scene.loads(SCENE.format(system="", seed=2**63 - 1)).seed == 2**63 - 1
    for depth in (9, 900, 5000):
        text = SCENE.format(system="x = " + "[" * depth + "]" * depth, seed=1)
        with pytest.raises(ParjamError, match="nested"):
            scene.loads(text)


def test_scene_names_name_their_files_inside_results():
    from parjam.study import plan, scene

    s = scene.loads('[scene]\nname = "../../X"\n' + SCENE.format(
        system='name = "../../ESC_SYS"', seed=1))
    assert (s.name, s.title) == ("___.._X", "../../X")
    assert (s.systems[0].name, s.systems[0].title) == ("___.._ESC_SYS", "../../ESC_SYS")
    for st in plan.plan(s):
        assert os.sep not in st.name
    assert "names its files '___.._ESC_SYS'" in plan.describe(s, plan.plan(s))
    two = SCENE.format(system='name = "a/b"', seed=1).replace(
        "[protocol]", '[[system]]\nd = 2\nN = 32\nname = "a_b"\n[protocol]')
    with pytest.raises(ParjamError, match="same file name"):
        scene.loads(two)


# --------------------------------------------------------------------------- pack

def _pack_args(*extra):
    from parjam import cli

    return cli.build_parser().parse_args(["pack", *extra])


def test_pack_refuses_two_values_with_one_label():
    from parjam.commands import pack

    args = _pack_args("--dim", "2", "--n", "16", "--dphi", "1e-2", "1.0004e-2")
    with pytest.raises(ParjamError, match="same state label dphi1.0e-02"):
        pack.validate(args)
    args = _pack_args("--dim", "2", "--n", "16", "--pressure", "1e-3", "1.04e-3")
    with pytest.raises(ParjamError, match="same state label p1.0e-03"):
        pack.validate(args)
    args = _pack_args("--dim", "2", "--n", "16", "--dphi", "1e-2", "1.1e-2")
    pack.validate(args)
    assert pack.state_labels(args) == ["phi_c", "dphi1.0e-02", "dphi1.1e-02"]


def test_pack_defaults_still_apply_and_from_refuses_what_the_file_decides():
    from parjam.commands import pack

    args = _pack_args()
    pack.validate(args)
    assert (args.dim, args.n, args.dispersity, args.ratio) == (3, 256, "mono", 1.4)
    for flag, value in (("--n", "100"), ("--dim", "3"), ("--dispersity", "bi"),
                        ("--ratio", "1.2"), ("--phi-start", "0.8")):
        with pytest.raises(ParjamError, match=f"{flag} cannot be given"):
            pack.validate(_pack_args("--from", os.path.join(DATA, hostile.PACKING), flag, value))


def test_a_quench_is_checked_against_the_round_off_only():
    from parjam.commands import pack

    pack.validate(_pack_args("--phi", "0.70", "--ftol", "5e-4"))  # no energy window is used
    with pytest.raises(ParjamError, match="not small against the contact forces"):
        pack.validate(_pack_args("--dphi", "1e-2", "--ftol", "5e-4"))  # the bisection is


def test_pack_refuses_a_member_file_linked_to_its_input(tmp_path):
    """In-process on both ranks (rank 0 looks, every rank raises): the --from file survives."""
    src = tmp_path / "in.h5"
    src.write_bytes(open(os.path.join(DATA, hostile.PACKING), "rb").read())
    before = src.read_bytes()
    od = tmp_path / "od"
    od.mkdir()
    os.symlink("../in.h5", od / "member0000_dphi1.0e-02.h5")
    rc, _, err = run_cli(["pack", "--from", str(src), "--dphi", "1e-2", "--out", str(od),
                          "--no-resume", "-q"])
    assert_one_line(rc, err)
    assert src.read_bytes() == before and os.path.islink(od / "member0000_dphi1.0e-02.h5")


# --------------------------------------------------------------------------- the window

def test_a_window_past_the_spectrum_holds_every_mode_once(shared_tmp):
    """--window 0,100 and 0,1e300: the d N' - d modes of a dense reference, none rejected (the
    deflated translations at 2 ||D||_inf stay out), exit 0; above the spectrum: one line."""
    import h5py
    import scipy.linalg

    from parjam.files import modes_io
    from parjam.files.h5md import read_packing
    from parjam.testing.reference import dense_system
    from parjam.vib.dense import dense_matrix

    path = os.path.join(DATA, hostile.PACKING)
    system = dense_system(read_packing(path))
    H = dense_matrix(system, "full")
    lam = scipy.linalg.eigvalsh(H)[system.d:]  # the d translations are the lowest (zero)
    norm = np.abs(H).sum(axis=1).max()
    for bounds in ("0,100", "0,1e300"):
        out = os.path.join(shared_tmp, f"window{bounds}.h5")
        rc, _, err = run_cli(["modes", path, "--window", bounds, "--out", out, "-q"])
        assert rc == 0 and "rejected" not in err and "Warning" not in err, err
        spec = modes_io.read_spectrum(out)
        assert len(spec["eigenvalue"]) == len(lam) == system.d * system.n - system.d
        assert np.allclose(spec["eigenvalue"], lam, rtol=0, atol=1e-12 * norm)
        with h5py.File(out, "r") as f:
            assert len(f["modes/rejected/eigenvalue"]) == 0
    rc, _, err = run_cli(["modes", path, "--window", "10,20", "--out",
                          os.path.join(shared_tmp, "above.h5"), "-q"])
    assert_one_line(rc, err)


# --------------------------------------------------------------------------- ranks end together

def test_group_failures_are_agreed_on_every_rank():
    """The last rank fails alone (as a group of its own would); every rank learns its line."""
    from mpi4py import MPI

    from parjam.ranks import GroupFailures

    comm = MPI.COMM_WORLD
    failing = comm.Get_size() - 1
    failures = GroupFailures(comm)
    mine = None
    if comm.Get_rank() == failing:
        mine = (3, "member 1: did not jam")
        failures.announce(*mine)
    comm.Barrier()
    if comm.Get_size() > 1 and comm.Get_rank() != failing:
        while not failures.pending():  # the notice arrives (non-blocking send)
            pass
    assert failures.agree(mine) == (3, "member 1: did not jam")
    assert GroupFailures(comm).agree(None) is None


def test_exit_codes_and_quiet_in_every_help():
    import pkgutil

    import parjam.commands

    for name in (m.name for m in pkgutil.iter_modules(parjam.commands.__path__)):
        rc, out, err = run_cli([name, "--help"])
        text = " ".join(out.split())
        assert rc == 0 and "exit status: 0 done; 2 bad input" in text, (name, err)
        assert "-q, --quiet" in text or name == "info", name
    rc, out, _ = run_cli(["modes", "--help"])
    assert "4 some requested modes did not converge" in " ".join(out.split())
