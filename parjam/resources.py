"""Will a plan fit this machine?  Memory and time estimates of ``pack`` and ``run`` checked
before the work starts (docs/explanation/reliability.md, "Sizes and the machine check").

- memory: the largest estimate per rank times the ranks on this node, against what the node
  can still give (MemAvailable of /proc/meminfo, and the cgroup v2/v1 limit minus its usage
  when one is set: batch systems confine jobs that way);
- time: the estimate in wall-clock seconds against the batch job's remaining time
  (``SLURM_JOB_END_TIME``), else ``PARJAM_TIME_LIMIT`` (seconds), else MAX_DAYS days: no batch
  system grants more, and a longer plan is a typing error (N = 5e7 instead of 5e4) far more
  often than an intent.

A plan that does not fit is refused with the reason (``--force`` runs it anyway); ``run
--dry-run`` prints the same verdict.  The estimates are deliberately rough (factor 2): they
catch plans that are off by orders of magnitude, not a plan 10 % over.
"""

import math
import os
import time

from parjam.errors import ParjamError

MAX_DAYS = 30.0
#: pack: peak resident memory of one process (MB) = BASE + PER_PARTICLE * N, from the measured
#: 1.15 GB of a 3D N = 10^5 ladder (docs/explanation/scaling.md) and ~150 MB for the interpreter
#: with PETSc, h5py and numpy loaded; the positions, neighbour lists, Hessian and checkpoints of
#: a member are not divided over the ranks that share it (conservative)
PACK_BASE_MB = 150.0
PACK_PER_PARTICLE_MB = 0.0105
#: the stability check of every returned state (parjam.pack.stability).  Its Lanczos test (the
#: default) keeps O(N) memory: the matrix, four vectors and the assembly's arrays, 4.6 kB per
#: particle in 3D (18 / 37 / 76 MB at N = 4096 / 8192 / 16384, phi = 0.70; docs/results/
#: stability.md).  Where that test is inconclusive, the exact inertia (a MUMPS LDL^T of the
#: full Hessian, its factor discarded, so its frontal stack) decides, but only up to
#: stability.EXACT_MAX_DOF = 100,000 rows (N = 33,333 in 3D): in 3D 745 MB at N = 32768, growing
#: as N^1.5 (measured 55 / 273 / 745 MB at N = 4096 / 13824 / 32768; docs/explanation/scaling.md,
#: "Counting without keeping the factor"), so below that size the model keeps the factor.  In
#: 2D the factor adds under 1 kB per particle (245 MB at N = 262,144), inside
#: PACK_PER_PARTICLE_MB.
PACK_CHECK_3D_MB = 745.0
PACK_CHECK_3D_N = 32768.0
PACK_CHECK_EXPONENT = 1.5
PACK_CHECK_EXACT_MAX_N = 100000.0 / 3.0
PACK_CHECK_LANCZOS_MB = 0.0046  # per particle in 3D; (d / 3)^2 of it in d dimensions


def pack_memory_mb(n, d=3):
    """Estimated peak memory of one pack process for a member of N particles in d dimensions
    (MB): the engine's arrays, plus the stability check (its exact fall-back's factorisation in
    3D where that may run)."""
    check = PACK_CHECK_LANCZOS_MB * (d / 3.0) ** 2 * float(n)
    if d == 3 and n <= PACK_CHECK_EXACT_MAX_N:
        check = max(check, PACK_CHECK_3D_MB * (float(n) / PACK_CHECK_3D_N) ** PACK_CHECK_EXPONENT)
    return PACK_BASE_MB + PACK_PER_PARTICLE_MB * float(n) + check


def pack_seconds(d, n, states, phic_method="bisect"):
    """Estimated one-core seconds of one member, for `pack` and the study planner
    (parjam.study.plan; measured: 3D N = 512 full ladder 10-25 s, 2D N = 1024 ~80 s; extrapolate
    0.4x: 3D N = 10240, five states, 710 s per member)."""
    per = 0.04 * float(n) ** 1.1 * (3.0 if d == 2 else 1.0) * (1 + 0.15 * max(states, 1))
    return per * (0.4 if phic_method == "extrapolate" else 1.0)


def _read_int(path):
    try:
        with open(path) as fh:
            text = fh.read().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def available_memory_mb():
    """What this node can still give (MB), or None if unknown."""
    avail = None
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    avail = int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    for limit_file, usage_file in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                                   ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
                                    "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        limit, usage = _read_int(limit_file), _read_int(usage_file)
        if limit is not None and limit < 1 << 60:
            left = (limit - (usage or 0)) / 2**20
            avail = left if avail is None else min(avail, left)
    override = os.environ.get("PARJAM_MEMORY_MB")  # tests and users who know better
    if override:
        avail = positive_setting("PARJAM_MEMORY_MB", override, "a number of megabytes")
    return avail


def positive_setting(name, text, what):
    """A PARJAM_* setting as a finite positive number: NaN would switch the check off (every
    comparison with it is false), infinity or a negative value make it meaningless."""
    try:
        value = float(text)
    except ValueError:
        raise ParjamError(f"{name}={text!r} is not {what}") from None
    if not math.isfinite(value) or value <= 0:
        raise ParjamError(f"{name}={text!r} must be {what} above 0 and finite")
    return value


def time_limit_seconds(now=None):
    """(seconds, where from) of the time the plan may take."""
    now = time.time() if now is None else now
    end = os.environ.get("SLURM_JOB_END_TIME")
    if end and end.isdigit() and int(end) > 0:
        return max(int(end) - now, 0.0), "the batch job's remaining time (SLURM_JOB_END_TIME)"
    text = os.environ.get("PARJAM_TIME_LIMIT")
    if text:
        return positive_setting("PARJAM_TIME_LIMIT", text, "a number of seconds"), \
            "PARJAM_TIME_LIMIT"
    return MAX_DAYS * 86400.0, "parjam's sanity limit"


def ranks_on_node(mpi):
    """How many ranks of ``mpi`` share this node (collective)."""
    from mpi4py import MPI

    if mpi.Get_size() == 1:
        return 1
    local = mpi.Split_type(MPI.COMM_TYPE_SHARED)
    try:
        return local.Get_size()
    finally:
        local.Free()


def _human(seconds):
    for unit, size in (("days", 86400.0), ("h", 3600.0), ("min", 60.0)):
        if seconds >= size:
            return f"{seconds / size:.3g} {unit}"
    return f"{seconds:.3g} s"


def verdict(memory_mb, wall_seconds, node_ranks, available_mb=None, limit=None):
    """Reasons why a plan needing ``memory_mb`` per rank (``node_ranks`` of them on this node)
    and ``wall_seconds`` does not fit; empty if it fits."""
    reasons = []
    if available_mb is not None and memory_mb * node_ranks > available_mb:
        reasons.append(f"needs ~{memory_mb * node_ranks / 1024:.3g} GB on this node "
                       f"({memory_mb / 1024:.3g} GB per rank x {node_ranks} rank(s)), "
                       f"{available_mb / 1024:.3g} GB available")
    if limit is not None and wall_seconds > limit[0]:
        reasons.append(f"would take ~{_human(wall_seconds)}, more than {limit[1]} "
                       f"({_human(limit[0])})")
    return reasons


def describe(memory_mb, wall_seconds, node_ranks):
    """The machine check as text (for --dry-run): 'fits' or why not."""
    reasons = verdict(memory_mb, wall_seconds, node_ranks, available_memory_mb(),
                      time_limit_seconds())
    if reasons:
        return "machine check: DOES NOT FIT: " + "; ".join(reasons) + \
            " (a real run refuses unless --force)"
    avail = available_memory_mb()
    return (f"machine check: fits (~{memory_mb * node_ranks / 1024:.3g} GB on this node of "
            f"{'?' if avail is None else f'{avail / 1024:.3g}'} GB available, "
            f"~{_human(wall_seconds)})")


def check(comm, memory_mb, wall_seconds, force, what):
    """Refuse (one line, every rank) a plan that does not fit, unless ``force``; rank 0 of
    ``comm`` decides, the ranks on its node count."""
    mpi = comm.tompi4py() if hasattr(comm, "tompi4py") else comm
    node = ranks_on_node(mpi)
    reasons, error = None, None
    if mpi.Get_rank() == 0:
        try:
            reasons = verdict(memory_mb, wall_seconds, node, available_memory_mb(),
                              time_limit_seconds())
        except ParjamError as exc:  # a bad PARJAM_* setting: every rank must hear it
            error = str(exc)
    if mpi.Get_size() > 1:
        reasons, error = mpi.bcast((reasons, error), root=0)
    if error:
        raise ParjamError(error)
    if reasons and not force:
        raise ParjamError(f"{what} does not fit this machine: {'; '.join(reasons)}; use --force "
                          f"to run it anyway")
    return reasons
