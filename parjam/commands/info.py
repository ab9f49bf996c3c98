"""``parjam info``: versions and capabilities of the installation."""


def add_parser(sub):
    p = sub.add_parser("info", help="versions of parjam, Python, numpy, PETSc, SLEPc, MPI")
    p.set_defaults(run=run)


def run(args):
    from mpi4py import MPI

    from parjam import env

    v = env.versions()
    comm = MPI.COMM_WORLD
    mumps = env.has_mumps()
    if comm.Get_rank() == 0:
        width = 10
        for key in ("parjam", "python", "numpy", "petsc", "slepc", "mpi4py", "mpi"):
            print(f"{key:<{width}} {v[key]}")
        print(f"{'PETSC_DIR':<{width}} {v['petsc_dir'] or '(petsc4py default)'}")
        print(f"{'ranks':<{width}} {comm.Get_size()}")
        print(f"{'MUMPS':<{width}} {'yes' if mumps else 'no'}")
    return 0
