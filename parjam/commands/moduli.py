"""``parjam moduli``: bulk and shear moduli and the stiffness tensor of a packing by linear
response (affine Born term minus the non-affine relaxation Xi^T D^+ Xi; see parjam.vib.moduli)."""

import os



def add_parser(sub):
    p = sub.add_parser(
        "moduli", help="elastic moduli B, G and the stiffness tensor by linear response",
        description="Remove rattlers, assemble the dynamical matrix D of the non-rattlers, solve "
        "D u = Xi for the force fields Xi of the d(d+1)/2 affine strains (PETSc KSP: CG with the "
        "translations as null space, preconditioned through D + tau I: on one rank by a "
        "Cholesky factorisation, MUMPS when available; on several by block Jacobi with an "
        "incomplete Cholesky ICC(0) block per rank, whose memory per rank does not grow with the "
        "rank count; options -moduli_ksp_* -moduli_pc_* -moduli_sub_pc_*, e.g. -moduli_pc_type "
        "gamg -moduli_pc_gamg_agg_nsmooths 0 for fewer iterations at about the same memory; "
        "GAMG's default smoothed aggregation costs 20-30 % more memory per rank on several "
        "ranks), and report the bulk modulus "
        "B = -V dp/dV, the isotropic shear modulus G, the smallest shear modulus over all "
        "directions (negative: unstable to some shear in the fixed box) and the residuals.")
    p.add_argument("packing", help="packing file (H5MD, from parjam pack)")
    p.add_argument("--out", help="write /moduli/* (tensors, moduli, solver report) to this file")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    p.set_defaults(run=run, reads=lambda a: [a.packing])


def run(args):
    from parjam import env
    from parjam.files import h5md, outputs, rowio
    from parjam.files import moduli as moduli_file
    from parjam.net import active
    from parjam.vib import moduli
    from parjam.progress import Progress

    PETSc = env.petsc()
    comm = PETSc.COMM_WORLD
    outputs.check(comm, files=[("--out", args.out)], inputs=[args.packing])
    progress = Progress(comm, args.quiet, "moduli: ")
    net = active.from_rows(comm, rowio.read_rows(comm, args.packing))  # this rank's rows only
    mod = moduli.compute(comm=comm, progress=progress, net=net)
    if args.out:
        prov = h5md.provenance(comm.getSize(), {
            "command": "moduli", "input": os.path.abspath(args.packing),
            "input_sha256": h5md.sha256(args.packing)})
        outputs.on_root(comm, lambda: moduli_file.write(args.out, mod, prov))
    if comm.getRank() == 0:
        print_summary(mod, args.out)
    return 0


def print_summary(mod, out):
    from parjam import units

    s = mod.summary()
    unstable = s["G_min"] < 0.0
    u = units.text("modulus", len(mod.stress))  # the stress tensor is d x d
    lines = [
        f"N' / Nc           {s['N_active']} / {s['Nc']}",
        f"pressure p        {s['pressure']:.6e} {u}",
        f"bulk modulus B    {s['B']:.6e} {u}   (affine {s['B_affine']:.6e})",
        f"shear modulus G   {s['G']:.6e} {u}   (affine {s['G_affine']:.6e})",
        f"G / B             {s['G_over_B']:.6e}",
        f"softest shear     {s['G_min']:.6e} {u}"
        + ("   UNSTABLE to some shear in this fixed box" if unstable else ""),
        f"solver            {mod.solver['ksp_type']}/{mod.solver['pc_type']}, iterations "
        f"{' '.join(str(i) for i in s['iterations'])}, max residual {s['max_residual']:.1e}",
    ]
    if out:
        lines.append(f"written           {out}")
    print("\n".join(lines), flush=True)
