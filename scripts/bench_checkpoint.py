#!/usr/bin/env python3
"""Memory of a checkpointed ``parjam pack`` member shared by P ranks, main's whole-file
checkpoint (OLD: positions and velocities gathered to every rank, written by rank 0 from an
in-memory HDF5 image) and this tree's checkpoint by rows (NEW: parjam.files.checkpointio) side by
side in one run (issue 18).  Run by hand, never in the test suite:

    source scripts/mpi-env
    nice -n 10 .venv/bin/python scripts/bench_checkpoint.py --old /work/main \
        --per-rank 25000 --ranks 1 2 4 --out docs/bench-checkpoint.md

Each point is ``mpirun -n P /usr/bin/time python DRIVER pack --dim 3 --n (per-rank x P)
--checkpoint-every 1e-9 ...`` with this tree's interpreter and the tree under test on
PYTHONPATH (bytecode not written: the old tree is only read); the driver stops the run with a
ParjamError after its WRITES-th checkpoint write (a FIRE snapshot every 100 steps of the first
quench: at this size the first minimisation outlasts the run), so every rank exits and reports
its peak resident set (max RSS).  The driver also instruments the checkpoint code:

- OLD: the bytes of rows (positions, velocities) in the image rank 0 writes, and the snapshot's
  gathers, which every rank holds: the (N, d) positions and (N, d) velocities;
- NEW: the largest piece rank 0 receives and writes at once (``rowio.RowFile.put``) and the
  largest block of rows any rank hands to the writer.
"""

import argparse
import json
import os
import re
import shutil
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PY = os.path.join(ROOT, ".venv", "bin", "python")
sys.path.insert(0, os.path.join(ROOT, "scripts"))

from peak_rss import measured  # noqa: E402

DRIVER = r"""
import json, os, sys
import numpy as np
from mpi4py import MPI
from parjam import cli; from parjam.pack import checkpoint
from parjam.errors import ParjamError

writes, stats = int(sys.argv[1]), {"rank0_piece": 0, "block": 0, "gathered": 0, "writes": 0}
# the tree under test (an editable install's finder would find checkpointio in another tree)
new = os.path.exists(os.path.join(os.path.dirname(checkpoint.__file__), "checkpointio.py"))
if new:
    from parjam.files import checkpointio, rowio
    put, write_rows = rowio.RowFile.put, checkpointio.write_rows

    def counting_put(self, name, axis, first, piece):
        stats["rank0_piece"] = max(stats["rank0_piece"], piece.nbytes)
        return put(self, name, axis, first, piece)

    def counting_rows(comm, path, blocks):
        stats["block"] = max(stats["block"], sum(np.asarray(b).nbytes for b in blocks.values()))
        return write_rows(comm, path, blocks)

    rowio.RowFile.put, checkpointio.write_rows = counting_put, counting_rows
else:
    write_file = checkpoint.write_file

    def counting_write(path, params, done, pending):
        rows = sum(r["pos"].nbytes for r in done)
        if pending is not None:
            rows += pending["pos"].nbytes + pending["state"].fire.v.nbytes
            stats["gathered"] = pending["pos"].nbytes + pending["state"].fire.v.nbytes
        stats["rank0_piece"] = max(stats["rank0_piece"], rows)
        return write_file(path, params, done, pending)

    checkpoint.write_file = counting_write
real = checkpoint.Checkpoint.write

def stopping(self):
    real(self)
    stats["writes"] += 1
    if stats["writes"] == writes:
        raise ParjamError("benchmark: stopped after %d checkpoint writes" % writes)

checkpoint.Checkpoint.write = stopping
code = cli.main(sys.argv[2:])
comm = MPI.COMM_WORLD
every = comm.gather(stats, root=0)
if comm.Get_rank() == 0:
    print("STATS " + json.dumps(every), flush=True)
"""

WRITE_COST = r"""
import json, sys, tempfile, time
import numpy as np
from parjam import env; from parjam.pack import checkpoint
from parjam.pack.forces import ForceField
from parjam.pack.minimize import MinResult

n, records = int(sys.argv[1]), int(sys.argv[2])
comm = env.petsc().COMM_WORLD
mpi = comm.tompi4py()
rng = np.random.default_rng(1)
L = 60.0
ff = ForceField(comm, np.ones(n), L, 3, 2.0)
lo, hi = ff.lo, ff.hi
ff.local(ff.x)[:] = rng.random((n, 3))[lo:hi] * L
out = mpi.bcast(tempfile.mkdtemp(prefix="bench-ckpt-w-") if mpi.Get_rank() == 0 else None)
ck = checkpoint.Checkpoint(checkpoint.path_for(out, 0), comm, 1e-9, {"bench": 1})
secs = []
for call in range(records):
    mpi.Barrier()
    t = time.perf_counter()
    ck.finish(call, ff, L, MinResult("converged", 0.0, 0.0), 1)
    mpi.Barrier()
    secs.append(time.perf_counter() - t)
ck.remove()
checkpoint.remove_empty_directory(out)
if mpi.Get_rank() == 0:
    print("SECS " + json.dumps(secs), flush=True)
"""


def write_cost(tree, ranks, n, records):
    """Seconds of each of ``records`` successive ``Checkpoint.finish`` calls (each written) at
    N particles on ``ranks`` ranks, and the peak RSS per rank."""
    argv = [PY, "-c", WRITE_COST, str(n), str(records)]
    mb, _, res = measured(ranks, argv, tree, env={"PYTHONPATH": tree, "OPENBLAS_NUM_THREADS": "1",
                                                  "PYTHONDONTWRITEBYTECODE": "1"},
                          cwd=tempfile.gettempdir())
    found = re.search(r"SECS (.*)", res.stdout)
    if not found:
        sys.stderr.write(res.stdout[-2000:] + res.stderr[-2000:])
        raise SystemExit(f"{tree}: the write-cost run failed")
    return mb, json.loads(found.group(1))


def point(tree, ranks, n, writes, seed):
    """(peak RSS per rank in MB, seconds, per-rank stats) of one checkpointed pack run."""
    out = tempfile.mkdtemp(prefix="bench-ckpt-")
    argv = [PY, "-c", DRIVER, str(writes), "pack", "--dim", "3", "--n", str(n),
            "--phic-method", "extrapolate", "--dphi", "1e-3", "--seed", str(seed),
            "--checkpoint-every", "1e-9", "--force", "-q", "--out", out]
    try:
        mb, secs, res = measured(ranks, argv, tree,
                                 env={"PYTHONPATH": tree, "OPENBLAS_NUM_THREADS": "1",
                                      "PYTHONDONTWRITEBYTECODE": "1"},
                                 cwd=tempfile.gettempdir())
    finally:
        shutil.rmtree(out, ignore_errors=True)
    found = re.search(r"STATS (.*)", res.stdout + res.stderr)
    if not found or "benchmark: stopped" not in res.stderr:
        sys.stderr.write(res.stdout[-2000:] + res.stderr[-2000:])
        raise SystemExit(f"{tree}, {ranks} ranks: the run did not reach {writes} writes")
    return mb, secs, json.loads(found.group(1))


def megabytes(b):
    return f"{b / 2**20:.2f}"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--old", required=True, help="a checkout of main (only read)")
    ap.add_argument("--per-rank", type=int, default=25000)
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--writes", type=int, default=3)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--write-n", type=int, default=100000)
    ap.add_argument("--write-ranks", type=int, nargs="*", default=[1, 2])
    ap.add_argument("--records", type=int, default=10)
    ap.add_argument("--out", default=os.path.join(ROOT, "docs", "bench-checkpoint.md"))
    args = ap.parse_args()
    rows = []
    for p in args.ranks:
        n = args.per_rank * p
        got = {}
        for name, tree in (("old", os.path.abspath(args.old)), ("new", ROOT)):
            got[name] = point(tree, p, n, args.writes, args.seed)
            mb, secs, _ = got[name]
            print(f"P={p} N={n} {name}: peak RSS per rank {[round(m) for m in mb]} MB, "
                  f"{secs:.0f} s", flush=True)
        rows.append((p, n, got))
    costs = []
    for p in args.write_ranks:
        got = {name: write_cost(tree, p, args.write_n, args.records)
               for name, tree in (("old", os.path.abspath(args.old)), ("new", ROOT))}
        print(f"write cost P={p}: {got}", flush=True)
        costs.append((p, got))
    lines = [
        "# Checkpoints by rows: memory per rank (issue 18)", "",
        "Generated by `scripts/bench_checkpoint.py` (" + " ".join(
            f"--{k.replace('_', '-')} {v if not isinstance(v, list) else ' '.join(map(str, v))}"
            for k, v in (("per_rank", args.per_rank), ("ranks", args.ranks),
                         ("writes", args.writes), ("seed", args.seed),
                         ("write_n", args.write_n), ("write_ranks", args.write_ranks),
                         ("records", args.records))) + "): "
        "`parjam pack --dim 3 --phic-method extrapolate --dphi 1e-3 --checkpoint-every 1e-9` "
        f"of one member shared by P ranks at {args.per_rank} particles per rank, stopped after "
        f"checkpoint write {args.writes} (FIRE snapshots of the first quench, every 100 "
        "steps).  OLD: main (the whole-file checkpoint); NEW: this tree (the index and pieces "
        "of parjam.files.checkpointio).  Ranks oversubscribed on a 2-core machine shared with other "
        "jobs: times are not comparable, memory is.", "",
        "Peak RSS: the largest over the ranks (max RSS of /usr/bin/time).  Rows held for a "
        "write: OLD, the rows in the HDF5 image rank 0 builds (all finished minimisations' "
        "positions + the snapshot's positions and velocities) and the snapshot's gathered "
        "positions + velocities every rank holds; NEW, the largest piece rank 0 receives and "
        "writes at once and the largest block of rows a rank hands to the writer.", "",
        "| P | N | peak RSS/rank old (MB) | new (MB) | new/old | rank 0 rows old (MB) | "
        "largest piece new (MB) | every rank gathers old (MB) | block new (MB) | s old | s new |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for p, n, got in rows:
        (mo, so, sto), (mn, sn, stn) = got["old"], got["new"]
        lines.append(
            f"| {p} | {n} | {max(mo):.1f} | {max(mn):.1f} | {max(mn) / max(mo):.3f} | "
            f"{megabytes(sto[0]['rank0_piece'])} | {megabytes(stn[0]['rank0_piece'])} | "
            f"{megabytes(max(s['gathered'] for s in sto))} | "
            f"{megabytes(max(s['block'] for s in stn))} | {so:.0f} | {sn:.0f} |")
    lines += ["", "Peak RSS of every rank (MB), old / new, in the order the ranks reported "
              "(not rank order):", ""]
    for p, n, got in rows:
        lines.append(f"- P = {p}: {[round(m, 1) for m in got['old'][0]]} / "
                     f"{[round(m, 1) for m in got['new'][0]]}")
    if costs:
        lines += [
            "", f"## The cost of a write at N = {args.write_n}", "",
            f"`Checkpoint.finish` called {args.records} times in a row on a random 3D "
            f"configuration of N = {args.write_n} (every call writes: old, the whole file with "
            "all the records so far; new, one piece and the index), the time of the first and "
            "of the last call, and the peak RSS per rank of the whole run (the records held: "
            "old, all of them on rank 0).", "",
            "| P | first write old (s) | new (s) | last write old (s) | new (s) | "
            "peak RSS/rank old (MB) | new (MB) |",
            "|---|---|---|---|---|---|---|"]
        for p, got in costs:
            (mo, so), (mn, sn) = got["old"], got["new"]
            lines.append(f"| {p} | {so[0]:.3f} | {sn[0]:.3f} | {so[-1]:.3f} | {sn[-1]:.3f} | "
                         f"{max(mo):.1f} | {max(mn):.1f} |")
    with open(args.out, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
