"""What every benchmark shares: running a command on P ranks with each rank's peak resident
set, the code of another commit (a ``git worktree``) beside this tree's, PETSc's ``-log_view``
read back, packings tiled to a size, and the results as JSON and as a markdown table (date,
machine, the command that reproduces it) written into a page of the docs.

No benchmark imports parjam's internals to measure it: parjam runs as its commands
(``python -P -m parjam ...`` with the tree under test first on PYTHONPATH), so the same
measurement runs on any commit.
"""

import contextlib
import datetime
import json
import os
import platform
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
import time

SCRIPTS = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ROOT = os.path.dirname(SCRIPTS)
DATA = os.path.join(ROOT, "tests", "data")
VENV_PY = os.path.join(ROOT, ".venv", "bin", "python")
PY = VENV_PY if os.path.exists(VENV_PY) else sys.executable

# Each rank runs its command as the child of this wrapper, which reports the child's peak
# resident set (wait4's ru_maxrss, kB on Linux) on stderr: /usr/bin/time -f %M, without the
# dependency.  The wrapper does not initialise MPI; the child inherits the launcher's variables.
WRAPPER = r"""
import os, sys
pid = os.fork()
if pid == 0:
    try:
        os.execvp(sys.argv[1], sys.argv[1:])
    finally:
        os._exit(127)
_, status, usage = os.wait4(pid, 0)
rank = os.environ.get("OMPI_COMM_WORLD_RANK", os.environ.get("PMI_RANK", "0"))
sys.stderr.write("PEAKRSS %s %d\n" % (rank, usage.ru_maxrss))
sys.exit(os.waitstatus_to_exitcode(status))
"""


def mpirun():
    """$PARJAM_MPIRUN split (scripts/mpi-env), else an oversubscribing mpirun."""
    return shlex.split(os.environ.get("PARJAM_MPIRUN", "mpirun --oversubscribe"))


class Run:
    """One command on ``ranks`` ranks: wall seconds, exit code (None: stopped at its timeout),
    peak RSS per rank in MB (rank order), and its output."""

    def __init__(self, ranks, seconds, returncode, rss_mb, stdout, stderr):
        self.ranks, self.seconds, self.returncode = ranks, seconds, returncode
        self.rss_mb, self.stdout, self.stderr = rss_mb, stdout, stderr

    @property
    def ok(self):
        return self.returncode == 0

    @property
    def peak(self):
        return max(self.rss_mb) if self.rss_mb else float("nan")

    def measured(self):
        """The columns every benchmark's row takes from a run: wall seconds, the largest peak
        RSS of a rank and every rank's (MB)."""
        return {"seconds": self.seconds, "peak_mb": self.peak, "rss_mb": self.rss_mb}

    @property
    def error(self):
        """A failed run's exit code and message: parjam's own last line (``parjam: ...``) if
        there is one, else the last line of stderr that is neither a memory report nor the
        launcher's frame."""
        lines = [ln.strip() for ln in self.stderr.splitlines()
                 if ln.strip().strip("-") and "PEAKRSS" not in ln]
        own = [ln for ln in lines if ln.startswith("parjam:")]
        text = (own or lines or [""])[-1][:200]
        return f"exit {self.returncode}: {text}" if text else f"exit {self.returncode}"


def run(argv, ranks=1, tree=ROOT, timeout=None, cwd=None, env=None):
    """``argv`` on ``ranks`` ranks of $PARJAM_MPIRUN, each rank under the memory wrapper, one
    thread per rank, ``tree``'s parjam first on the path.  ``argv[0] == "parjam"`` runs
    ``python -P -m parjam`` (-P: the working directory never shadows ``tree``)."""
    if argv[0] == "parjam":
        argv = [PY, "-P", "-m", "parjam"] + list(argv[1:])
    cmd = mpirun() + ["-n", str(ranks), PY, "-c", WRAPPER] + [str(a) for a in argv]
    environ = dict(os.environ, PYTHONPATH=os.pathsep.join([tree, SCRIPTS]), OMP_NUM_THREADS="1",
                   OPENBLAS_NUM_THREADS="1", OMPI_MCA_rmaps_base_oversubscribe="1",
                   OMPI_MCA_mpi_yield_when_idle="1", **(env or {}))
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=environ, cwd=cwd or tempfile.gettempdir(),
                            start_new_session=True)
    try:
        out, err = proc.communicate(timeout=timeout)
        code = proc.returncode
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, 15)  # the launcher and its ranks
        out, err = proc.communicate()
        code = None
        err += f"\nstopped after {timeout:.0f} s"
    seconds = time.perf_counter() - t0
    found = sorted((int(r), int(kb)) for r, kb in re.findall(r"PEAKRSS (\d+) (\d+)", err))
    return Run(ranks, seconds, code, [kb / 1024.0 for _, kb in found], out, err)


def floor_mb(ranks, tree=ROOT):
    """Peak RSS per rank (largest) of a process that only starts parjam, PETSc and MPI: the part
    of every measurement no code can save."""
    return run([PY, "-P", "-c", "from parjam import env; env.init()"], ranks, tree).peak


# --- the code under test ---------------------------------------------------------------------
def git(*args, repo=ROOT):
    return subprocess.run(["git", "-C", repo, *args], check=True, capture_output=True,
                          text=True).stdout.strip()


def describe(tree=ROOT):
    """Short commit of ``tree``, with ``+changes`` when its working tree differs from it."""
    try:
        sha = git("rev-parse", "--short", "HEAD", repo=tree)
        return sha + ("+changes" if git("status", "--porcelain", "--", "parjam", repo=tree)
                      else "")
    except (subprocess.CalledProcessError, FileNotFoundError):
        return "unknown"


@contextlib.contextmanager
def trees(old=None, repo=ROOT):
    """[(label, tree)]: this tree as ``new``, and with ``old`` (a commit of ``repo``) first a
    ``git worktree`` of it as ``old``, removed afterwards.  Its compiled kernel is built on first
    use into $PARJAM_CACHE (parjam.pack.kernels)."""
    if not old:
        yield [("new", ROOT)]
        return
    tmp = tempfile.mkdtemp(prefix="parjam-bench-old-")
    path = os.path.join(tmp, "tree")
    git("worktree", "add", "--detach", "--quiet", path, old, repo=repo)
    try:
        found = subprocess.run([PY, "-P", "-c", "import parjam; print(parjam.__file__)"],
                               capture_output=True, text=True,
                               env=dict(os.environ, PYTHONPATH=path)).stdout.strip()
        if not found.startswith(path + os.sep):  # an install shadowing PYTHONPATH
            raise SystemExit(f"bench: the old tree's parjam is not the one imported ({found})")
        yield [("old", path), ("new", ROOT)]
    finally:
        git("worktree", "remove", "--force", path, repo=repo)
        shutil.rmtree(tmp, ignore_errors=True)


# --- inputs and outputs of the runs ----------------------------------------------------------
def packing(spec, work):
    """A packing file from ``PATH`` or ``PATH:K`` (PATH tiled K^d times by tile_packing.py, made
    once in ``work``); a relative PATH is taken from the checkout."""
    path, _, k = spec.partition(":")
    path = os.path.join(ROOT, path) if not os.path.isabs(path) else path
    if not os.path.exists(path):
        raise SystemExit(f"bench: no packing {path}")
    if not k or int(k) == 1:
        return path
    out = os.path.join(work, f"{os.path.splitext(os.path.basename(path))[0]}_x{k}.h5")
    if not os.path.exists(out):
        made = subprocess.run([PY, os.path.join(SCRIPTS, "tile_packing.py"), path, k, out],
                              capture_output=True, text=True, env=dict(os.environ,
                                                                         PYTHONPATH=ROOT))
        if made.returncode:
            raise SystemExit(f"bench: cannot tile {spec}: {made.stderr.strip()[-300:]}")
    return out


def log_view(path):
    """PETSc's ``-log_view`` text read back: ({stage: seconds}, {event: (count, seconds)}), the
    largest time over the ranks, each event summed over the stages."""
    stages, events = {}, {}
    with open(path) as fh:
        text = fh.read().split("Memory usage is given in bytes")[0]
    for line in text.splitlines():
        m = re.match(r"^\s*\d+:\s+(.+?):\s+(\d\.\d+e[+-]\d+)\s+\d", line)
        if m:
            stages[m.group(1)] = float(m.group(2))
            continue
        m = re.match(r"^(\S.*?)\s+(\d+)\s+\d+\.\d\s+(\d\.\d{4}e[+-]\d\d)\s", line)
        if m:
            count, secs = events.get(m.group(1), (0, 0.0))
            events[m.group(1)] = (count + int(m.group(2)), secs + float(m.group(3)))
    return stages, events


def variants(specs):
    """``LABEL: ARGS`` strings as [(label, [args])]; ARGS may hold ``{work}``."""
    out = []
    for spec in specs:
        label, _, rest = spec.partition(":")
        out.append((label.strip(), shlex.split(rest)))
    return out


def label(spec):
    """A packing argument (``PATH`` or ``PATH:K``) as the page shows it, PATH relative to the
    checkout when inside it."""
    path, sep, k = spec.partition(":")
    return relpath(path if os.path.isabs(path) else os.path.join(ROOT, path)) + sep + k


def relpath(path):
    """A path as the page shows it: relative to the checkout when inside it."""
    path = os.path.abspath(path)
    return os.path.relpath(path, ROOT) if path.startswith(ROOT + os.sep) else path


# --- results and the page --------------------------------------------------------------------
def machine():
    """Cores, CPU model and memory of this machine, in one line."""
    model, mem = platform.processor() or platform.machine(), ""
    with contextlib.suppress(OSError):
        with open("/proc/cpuinfo") as fh:
            model = next((ln.split(":", 1)[1].strip() for ln in fh
                          if ln.startswith("model name")), model)
        with open("/proc/meminfo") as fh:
            mem = f", {int(fh.readline().split()[1]) / 2**20:.0f} GB"
    return f"{os.cpu_count()} cores ({model}){mem}, {platform.system()} {platform.release()}"


def meta(name, command, old=None):
    return {"benchmark": name, "date": datetime.datetime.now(datetime.timezone.utc)
            .strftime("%Y-%m-%d %H:%M UTC"), "machine": machine(), "command": command,
            "commit": describe(), "old": old, "load": os.getloadavg()[0]}


BEGIN, END = "<!-- bench {}: begin -->", "<!-- bench {}: end -->"


def fmt(value, spec):
    if value is None or (isinstance(value, float) and value != value):
        return "-"
    if spec.endswith("d") and isinstance(value, float):  # numpy integers come back as floats
        value = int(round(value))
    return format(value, spec) if spec else str(value)


def section(mod, result):
    """The markdown of one result: how it was measured, the table, the benchmark's notes."""
    m = result["meta"]
    old = f" against {m['old']} (`old`)" if m.get("old") else ""
    lines = [BEGIN.format(m["benchmark"]),
             f"Measured {m['date']}, parjam {m['commit']}{old}; {m['machine']}; load average "
             f"{m['load']:.1f} at the start, {m.get('load_end', float('nan')):.1f} at the end.",
             "", "```sh", m["command"], "```", "",
             "| " + " | ".join(head for head, _, _ in mod.COLUMNS) + " |",
             "|" + "---|" * len(mod.COLUMNS)]
    for row in result["rows"]:
        cells = [fmt(key(row) if callable(key) else row.get(key), spec)
                 for _, key, spec in mod.COLUMNS]
        lines.append("| " + " | ".join(cells) + " |")
    notes = mod.notes(result["rows"]) if hasattr(mod, "notes") else []
    return "\n".join(lines + ([""] + notes if notes else []) + [END.format(m["benchmark"])])


def write_doc(page, name, text):
    """Put ``text`` between the benchmark's markers of ``page`` (appended when it has none)."""
    doc = open(page).read() if os.path.exists(page) else ""
    begin, end = BEGIN.format(name), END.format(name)
    if begin in doc and end in doc:
        doc = doc[:doc.index(begin)] + text + doc[doc.index(end) + len(end):]
    else:
        doc = doc.rstrip("\n") + ("\n\n" if doc else "") + text + "\n"
    with open(page, "w") as fh:
        fh.write(doc)


def save(path, result):
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as fh:
        json.dump(result, fh, indent=1, default=float)
