#!/usr/bin/env python3
"""Per-phase costs of parjam on one packing, for the scaling model of docs/explanation/scaling.md.

    source scripts/mpi-env
    $PARJAM_MPIRUN -n 2 .venv/bin/python scripts/hpc/profile_phases.py P.h5 --json out.json \
        -log_view :log_view.txt

Each phase runs inside its own PETSc log stage (so ``-log_view`` shows its events, flops and
messages per stage) and is timed between barriers:

- ``phase: neighbours``  one Verlet-list rebuild of the ForceField (the cell search on one
                         rank, the slab search on several) and its halo
- ``phase: force``       ``--forces`` force evaluations (the minimiser's unit of work)
- ``phase: assembly``    the distributed MatAIJ of the full dynamical matrix (hessian.assemble)
- ``phase: factor``      MUMPS LDL^T (Cholesky) of D - target I on SBAIJ, as ``modes`` does
                         (symbolic + numeric), with the MUMPS fill and flops
- ``phase: solve``       ``--solves`` forward/backward solves with that factor (one per
                         shift-and-invert Krylov step)
- ``phase: matvec``      ``--matvecs`` MatMult (one per two KPM moments)

Rank 0 prints one JSON record (and writes it to --json, appending to a list).
"""

import argparse
import json
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(os.path.dirname(HERE)))

import numpy as np  # noqa: E402


def timed(comm, name, fn, repeat=1):
    """Run fn() ``repeat`` times inside the log stage ``phase: name``; seconds per call."""
    from parjam.logstage import log_stage

    comm.barrier()
    with log_stage(f"phase: {name}"):
        t0 = time.perf_counter()
        for _ in range(repeat):
            out = fn()
        comm.barrier()
        sec = (time.perf_counter() - t0) / repeat
    return sec, out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("packing")
    ap.add_argument("--forces", type=int, default=100)
    ap.add_argument("--solves", type=int, default=40)
    ap.add_argument("--matvecs", type=int, default=200)
    ap.add_argument("--json", help="append the record to this JSON list (rank 0)")
    args, petsc_args = ap.parse_known_args()  # PETSc options (-log_view ...) pass through

    from parjam import env
    from parjam.files import h5md
    from parjam.vib import spectrum
    from parjam.pack.forces import ForceField

    env.init(petsc_args)
    PETSc = env.petsc()
    comm = PETSc.COMM_WORLD
    mpi = comm.tompi4py()
    pack = h5md.read_packing(args.packing)
    rec = {"file": args.packing, "N": pack.n, "d": pack.d, "ranks": comm.getSize()}

    ff = ForceField(comm, pack.diam, pack.L, pack.d, pack.alpha, pack.eps)
    ff.set_positions(pack.pos)
    f = ff.vec()

    def neighbours():
        ff.rebuild_neighbours()

    rec["neighbours_s"], _ = timed(mpi, "neighbours", neighbours)
    rec["force_s"], _ = timed(mpi, "force", lambda: ff.evaluate(f), args.forces)
    f.destroy()
    ff.destroy()

    system = spectrum.system_of(comm, pack)
    rec.update({"N_active": system.n, "contacts": system.n_contacts, "dof": system.dof})
    rec["assembly_s"], A = timed(mpi, "assembly",
                                 lambda: spectrum.dynamical_matrix(comm, system, "full"))
    norm = A.norm(PETSc.NormType.INFINITY)
    shift = spectrum.ZERO_TOL * norm  # D - target I with target = -zero_tol, as modes does
    A.shift(shift)
    S = A.convert("sbaij")
    ksp = PETSc.KSP().create(comm)
    ksp.setOperators(S)
    ksp.setType("preonly")
    pc = ksp.getPC()
    pc.setType("cholesky")
    pc.setFactorSolverType("mumps")
    ksp.setOptionsPrefix("profile_")
    ksp.setFromOptions()
    rec["factor_s"], _ = timed(mpi, "factor", ksp.setUp)
    rec.update({f"mumps_{k}": v for k, v in spectrum.mumps_stats(pc.getFactorMatrix()).items()})
    b, x = A.createVecs()
    b.setRandom()
    rec["solve_s"], _ = timed(mpi, "solve", lambda: ksp.solve(b, x), args.solves)
    rec["matvec_s"], _ = timed(mpi, "matvec", lambda: A.mult(b, x), args.matvecs)
    rec["nnz"] = int(A.getInfo()["nz_used"])
    for obj in (ksp, S, A, b, x):
        obj.destroy()
    if mpi.Get_rank() == 0:
        print(json.dumps(rec), flush=True)
        if args.json:
            old = []
            if os.path.exists(args.json):
                with open(args.json) as fh:
                    old = json.load(fh)
            old.append(rec)
            with open(args.json, "w") as fh:
                json.dump(old, fh, indent=1)


if __name__ == "__main__":
    main()
