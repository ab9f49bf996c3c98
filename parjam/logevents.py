"""PETSc log events around the packing engine's hot spots, so that ``-log_view`` shows where a
packing spends its time (next to the stages of parjam.pack.packing.log_stage):

  parjam: force kernel      the compiled pair kernel / fused FIRE step (parjam.pack.kernels)
  parjam: FIRE allreduce    the one reduction of a fused FIRE step (the step's synchronisation)
  parjam: nbr rebuild       a Verlet-list rebuild (the engine's: migration, ghost plan, search)
  parjam: nbr search        the compiled pair search inside a rebuild (cells, stencil, sort
                            into (i, j) order), one per rebuild: the rest of a rebuild is the
                            hand-over and the ghost plan
  parjam: halo exchange     the engine's ghosts: their forces sent before the allreduce and
                            received after it (two per FIRE step), their positions and
                            velocities pulled at a rebuild; Newton's ghost positions
  parjam: migration         the engine's hand-over of particles to the slabs that own them
  parjam: Newton assembly   the Hessian's assembly for a Newton step
  parjam: Newton factor     the factorisation (or preconditioner set-up) of a Newton step
  parjam: stab Lanczos      the stability check's Lanczos test (parjam.pack.stability)
  parjam: stab inertia      the stability check's exact inertia (MUMPS LDL^T)

All events are registered together, in this order, the first time one is used, so every rank
numbers them alike.
"""

from parjam import env

FORCE = "parjam: force kernel"
ALLREDUCE = "parjam: FIRE allreduce"
REBUILD = "parjam: nbr rebuild"
HALO = "parjam: halo exchange"
ASSEMBLY = "parjam: Newton assembly"
FACTOR = "parjam: Newton factor"
MIGRATE = "parjam: migration"
STABILITY_LANCZOS = "parjam: stab Lanczos"
STABILITY_INERTIA = "parjam: stab inertia"
SEARCH = "parjam: nbr search"
NAMES = (FORCE, ALLREDUCE, REBUILD, HALO, ASSEMBLY, FACTOR, MIGRATE, STABILITY_LANCZOS,
         STABILITY_INERTIA, SEARCH)

_events = {}


def event(name):
    """The PETSc.Log.Event ``name`` (one of NAMES): use as ``with event(FORCE): ...``."""
    if not _events:
        PETSc = env.petsc()
        for n in NAMES:
            _events[n] = PETSc.Log.Event(n)
    return _events[name]
