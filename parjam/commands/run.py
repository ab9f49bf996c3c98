"""``parjam run scene.toml``: a whole study from a scene file (parjam.scene), stage by stage.

Layout of ``--out`` (default ``results/<scene name>``):

    stages/<stage name>/member0000_<state>.h5   packings (pack stages, the ``parjam pack`` files)
    stages/<stage name>/member0000.h5           one file per member of every analysis stage
    summary-<system>-<key>.h5                    ensemble means, errors and D(omega) averages
    stage.log                                    one line per member computed (never per skip)
    figures/*.png                                with [observables.pictures]

A stage's name ends with the hash of its inputs (system, protocol, seed, solver choices and the
keys of the stages it reads), so a changed scene recomputes exactly the stages whose inputs
changed.  A member's file is written atomically when the member is finished: re-running skips
finished members and stages, and an interrupted stage resumes at the first unfinished member.
Members are spread over groups of ranks (member m to group m % groups); with fewer members than
ranks a group shares a member (distributed minimisation, distributed matrices).
"""

import argparse
import collections
import os
import sys
import time
import warnings

import numpy as np

from parjam.errors import ParjamError

#: what this process computed, by kind (tests check that a scene computes only what it needs)
COUNTERS = collections.Counter()
EXIT_INTERRUPTED = 5


def add_parser(sub):
    p = sub.add_parser(
        "run", help="run a scene: packings, spectra and observables described in a TOML file",
        description="Plan the stages a scene's observables need (parjam.scene), then compute "
        "them member by member, storing each result in HDF5 as it finishes; re-running skips "
        "what is done and resumes an interrupted stage. --dry-run prints the plan.")
    p.add_argument("scene", help="scene file (TOML)")
    p.add_argument("--dry-run", action="store_true",
                   help="print the plan (stages, sizes, solver per stage, estimates) and stop")
    p.add_argument("--out", help="output directory (default results/<scene name>)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    p.set_defaults(run=run)


def run(args):
    from parjam import env, scene as sc
    from parjam.progress import Progress

    scene = sc.load(args.scene)
    stages = sc.plan(scene)
    PETSc = env.petsc()
    world = PETSc.COMM_WORLD
    if args.dry_run:
        if world.getRank() == 0:
            print(sc.describe(scene, stages), flush=True)
        return 0
    out = args.out or os.path.join("results", scene.name)
    progress = Progress(world.tompi4py(), args.quiet, "run: ")
    runner = Runner(scene, stages, out, world, progress)
    code = runner.run()
    if world.getRank() == 0 and code == 0:
        print(runner.report(), flush=True)
    return code


# --------------------------------------------------------------------------- ranks and files

def member_groups(world, members):
    """min(members, ranks) groups of ranks; member m belongs to group m % groups."""
    from parjam import env

    mpi = world.tompi4py()
    ngroups = min(members, mpi.Get_size())
    color = mpi.Get_rank() * ngroups // mpi.Get_size()
    sub = mpi.Split(color, mpi.Get_rank())
    return env.petsc().Comm(sub), [m for m in range(members) if m % ngroups == color]


def write_part(path, data, attrs=None):
    """{state: {name: array or scalar}} -> /<state>/<name>, atomically."""
    from parjam import io

    with io.atomic_h5(path) as f:
        for key, val in (attrs or {}).items():
            f.attrs[key] = val
        for state, values in data.items():
            g = f.create_group(state)
            for name, val in values.items():
                if isinstance(val, str):
                    g.attrs[name] = val
                else:
                    g.create_dataset(name, data=np.asarray(val))


def read_part(path):
    import h5py

    with h5py.File(path, "r") as f:
        return {state: {**{k: v[()] for k, v in f[state].items()}, **dict(f[state].attrs)}
                for state in f}


# --------------------------------------------------------------------------- per-state work

def pack_args(scene, system, out):
    """The parjam.ensemble.pack_member arguments of a scene's packing stage."""
    p = scene.protocol
    return argparse.Namespace(
        dim=system.d, n=system.n, alpha=system.alpha, dispersity=system.dispersity,
        ratio=system.ratio, phi=None, phi_start=p.phi_start or {2: 0.86, 3: 0.66}[system.d],
        seed=scene.seed, ftol=p.ftol, energy_window=tuple(p.energy_window), no_phic_file=False,
        pressure=p.pressure, dphi=p.dphi, ladder=p.ladder, out=out, members=scene.members,
        quiet=False, phic_method=p.phic_method)


def network_record(pack):
    """z, dz, p and the rest of the contact-network summary (parjam.network)."""
    from parjam.network import analyze

    COUNTERS["network"] += 1
    rec = dict(analyze(pack).summary())
    rec["phi_c"] = float(pack.meta.get("phi_c", np.nan))
    # 1 for a stable minimum, 0 for a state the packing protocol could not make one (flagged,
    # kept: parjam.packing.Jammer.stabilise); NaN for files written before the check existed
    rec["stable"] = float(pack.meta.get("stable", np.nan))
    # dz measured from the isostatic count, 2 (Nc - Nc_iso) / N': z - 2d without its finite-size
    # offset -2d/N' (z = 2d - 2d/N' + 2/N' at isostaticity in a periodic box)
    rec["dz_iso"] = 2.0 * rec["excess"] / rec["N_active"] if rec["N_active"] else np.nan
    return rec


def dense_eigenvalues(comm, system, kind):
    """All eigenvalues of one matrix without eigenvectors (LAPACK eigvalsh of the deflated dense
    matrix, parjam.spectrum's dense reference without its vectors): rank 0 computes, all get."""
    from parjam import spectrum

    mpi = comm.tompi4py()
    res = None
    if mpi.Get_rank() == 0:
        H = spectrum.dense_matrix(system, kind)
        norm = float(np.abs(H).sum(axis=1).max())
        lam, _ = spectrum.dense_eigh(spectrum.deflated_dense(H, system.n, system.d, norm),
                                     k=system.n_modes, vectors=False)
        res = (lam, norm)
    return mpi.bcast(res, root=0)


def spectrum_record(comm, pack, kind, req, tol):
    """The spectrum a state needs (req from parjam.scene.spectrum_needs, with its solver), with
    D0 and omega* (parjam.observables) and the per-mode sums when they were computed."""
    from parjam import observables, spectrum

    system = spectrum.active_system(pack)
    sol = req["solver"]
    COUNTERS[f"eigensolve:{sol}"] += 1
    rec = {"solver": sol, "n_modes_total": system.n_modes, "n_active": system.n}
    if sol == "dense-eigvalsh":
        lam, norm = dense_eigenvalues(comm, system, kind)
        rec.update(eigenvalue=lam, error=np.full(len(lam), np.nan), norm=norm,
                   n_negative=int(np.sum(lam < -spectrum.ZERO_TOL * norm)), complete=True)
    else:
        specs = []
        if sol == "dense-eigh":
            specs.append(spectrum.compute(comm, system, kind, k=system.n_modes, method="dense",
                                          tol=tol, vectors=req["vectors"]))
        if sol in ("slice", "slice+sinvert"):
            specs.append(spectrum.compute(comm, system, kind, window=req["window"],
                                          method="slice", tol=tol, vectors=req["vectors"]))
        if sol in ("sinvert", "slice+sinvert"):
            specs.append(spectrum.compute(comm, system, kind, k=min(req["k"], system.n_modes),
                                          method="sinvert", tol=tol, vectors=req["vectors"]))
        lam = np.concatenate([s.eigenvalue for s in specs])
        lam, first = np.unique(lam, return_index=True)

        def cat(name):
            return np.concatenate([getattr(s, name) for s in specs])[first]

        rec.update(eigenvalue=lam, error=cat("error"), eps_perp=cat("eps_perp"),
                   eps_par=cat("eps_par"), participation_ratio=cat("participation_ratio"),
                   norm=specs[0].norm, n_negative=max(s.n_negative for s in specs),
                   complete=all(s.complete for s in specs))
        if req["vectors"] and comm.getRank() == 0:
            rec["eigenvector"] = np.concatenate([s.vectors for s in specs])[first]
        if req["window"] is not None and sol == "dense-eigh":  # the dense path computed all
            rec["window"] = np.array(req["window"], dtype=float)
    omega = observables.frequency(rec["eigenvalue"])
    rec["frequency"] = omega
    pos = omega[omega > 0]
    if req.get("kpm_plateau") and not sol.startswith("dense"):  # a partial spectrum
        d0, wstar, window = kpm_plateau_summary(comm, system, kind, pos)
        rec["plateau_source"] = "kpm"
    else:
        try:
            d0, wstar, window = observables.dos_summary(pos, system.n_modes)
        except ParjamError:
            d0, wstar, window = np.nan, np.nan, (np.nan, np.nan)
    rec.update(D0=d0, omega_star=wstar, plateau_window=np.array(window, dtype=float),
               omega_min=float(pos.min()) if len(pos) else np.nan,
               pressure=system.pressure, complete=bool(rec["complete"]))
    return rec


KPM_PLATEAU = {"n_moments": 512, "n_probes": 16, "seed": 0}


def kpm_plateau_summary(comm, system, kind, omega):
    """(D0, omega*, plateau window) of a partial spectrum (the lowest modes or a window): the
    plateau D0 from KPM moments of the whole matrix (parjam.kpm, the 30-60 % frequency
    quantiles), omega* from the computed modes with it (parjam.observables.omega_star: N(omega)
    is exact up to the highest computed mode; NaN if the modes do not reach 2 omega*).  The
    partial spectrum's own upper half would bias D0, and omega* with it, low: by 5-20 % at
    dphi = 1e-5 .. 1e-3 (3D, N = 1024, docs/reproduction.md)."""
    from parjam import kpm, observables

    COUNTERS["kpm"] += 1
    res = kpm.compute(comm, system, kind, **KPM_PLATEAU)
    d0, _, window = kpm.dos_summary(res)
    return d0, observables.omega_star(omega, system.n_modes, d0), window


def moduli_record(comm, pack):
    from parjam import moduli

    COUNTERS["moduli"] += 1
    mod = moduli.compute(pack, comm)
    rec = {k: v for k, v in mod.summary().items() if v is not None and np.isscalar(v)}
    rec["stiffness"] = mod.stiffness
    return rec


def softmodes_record(comm, pack, opts):
    from parjam import softmodes as sm

    COUNTERS["softmodes"] += 1
    planes = [sm.parse_cut(c, pack.d) for c in opts["cuts"]]
    if opts["subdivide"] is not None:
        planes += sm.subdivision_planes(opts["subdivide"], pack.d)
    cs = sm.prepare(pack, list(dict.fromkeys(planes)), opts["allow_hyperstatic"])
    res = sm.analyse(comm, cs, opts["e0"], opts["bins"])
    rec = {k: (np.nan if v is None else v) for k, v in res.summary().items()}
    rec.update(overlap=res.overlap, extension=res.e, trial_energy=res.trial_energy,
               extended_fraction=res.fractions, L=cs.L, n_planes=len(cs.planes))
    return rec


def contact_fluctuations(pack, max_divisions):
    """The seed's connectivity-fluctuation argument: split the box into m^d sub-boxes of side
    l = L/m (m = 1..max_divisions), count in each the contacts among non-rattlers (by the
    contact's midpoint) and the non-rattlers, and return l, the variance of the contact count
    and the variance of the excess count dN_c = N_c - (z/2) N_box (fluctuation at fixed
    particle number), over the sub-boxes."""
    from parjam.network import analyze
    from parjam.system import wrap

    net = analyze(pack)
    c = net.contacts
    mid = wrap(pack.pos[c.i] + 0.5 * c.rij, pack.L)
    act = pack.pos[~net.rattler]
    half_z = 0.5 * net.z
    rows = []
    for m in range(1, max_divisions + 1):
        if m > 1 and pack.L / m < 2.0 * pack.diam.max():
            break

        def box_index(x):
            k = np.minimum((x / pack.L * m).astype(int), m - 1)
            return np.ravel_multi_index(k.T, (m,) * pack.d)

        nc = np.bincount(box_index(mid), minlength=m ** pack.d).astype(float)
        npart = np.bincount(box_index(act), minlength=m ** pack.d).astype(float)
        excess = nc - half_z * npart
        rows.append((pack.L / m, nc.mean(), nc.var(), excess.var(), npart.mean()))
    arr = np.array(rows)
    return {"l": arr[:, 0], "mean_contacts": arr[:, 1], "var_contacts": arr[:, 2],
            "var_excess": arr[:, 3], "mean_particles": arr[:, 4], "dz": net.dz,
            "L": pack.L}


# --------------------------------------------------------------------------- the runner

class Runner:
    def __init__(self, scene, stages, out, world, progress, stop_after=None):
        self.scene, self.stages, self.out = scene, stages, out
        self.world, self.mpi = world, world.tompi4py()
        self.progress = progress
        #: stop (as if interrupted) after this many members computed in this process
        self.stop_after = stop_after
        self.computed = 0
        self.summaries = {}
        self.pack_dirs = {}
        self.counts = collections.Counter()

    # paths -------------------------------------------------------------------
    def stage_dir(self, st):
        return os.path.join(self.out, "stages", st.name)

    def part_path(self, st, m):
        return os.path.join(self.stage_dir(st), f"member{m:04d}.h5")

    def pack_path(self, system, m, label):
        return os.path.join(self.pack_dirs[system.name], f"member{m:04d}_{label}.h5")

    def summary_path(self, st):
        return os.path.join(self.out, f"summary-{st.system.name}-{st.key}.h5")

    def failed_path(self, system, m):
        return os.path.join(self.pack_dirs[system.name], f"member{m:04d}.failed")

    def failed(self, system, m):
        """The member's packing could not be made (it did not jam): left out of everything."""
        return os.path.isfile(self.failed_path(system, m))

    def member_done(self, st, m):
        if self.failed(st.system, m):
            return True
        if st.kind == "pack":
            d = self.stage_dir(st)
            return all(os.path.isfile(os.path.join(d, f"member{m:04d}_{lab}.h5"))
                       for lab in st.states)
        return os.path.isfile(self.part_path(st, m))

    def log(self, st, m):
        with open(os.path.join(self.out, "stage.log"), "a") as fh:
            fh.write(f"{time.strftime('%Y-%m-%dT%H:%M:%S')} computed {st.name} member {m}\n")

    # the loop ----------------------------------------------------------------
    def run(self):
        from parjam import env

        PETSc = env.petsc()
        if self.mpi.Get_rank() == 0:
            os.makedirs(self.out, exist_ok=True)
        self.mpi.Barrier()
        comm, mine = member_groups(self.world, self.scene.members)
        self.comm = comm
        stage = PETSc.Log.Stage("parjam run")
        stage.push()
        stopped = False
        try:
            for st in self.stages:
                if st.kind == "pack":
                    self.pack_dirs[st.system.name] = self.stage_dir(st)
                if st.kind == "summary":
                    # a member's stages all run in the same group, so groups only wait for each
                    # other here, where the summary reads every member
                    if self.mpi.allreduce(stopped, op=_lor()):
                        self.progress("interrupted: re-run the same command to resume")
                        return EXIT_INTERRUPTED
                    self.summarise(st)
                elif not stopped:
                    stopped = self.run_stage(st, comm, mine)
        finally:
            stage.pop()
        if "pictures" in self.scene.observables and self.mpi.Get_rank() == 0:
            self.pictures()
        self.mpi.Barrier()
        return 0

    def run_stage(self, st, comm, mine):
        """This group's unfinished members of one stage; True if stopped early."""
        gm = comm.tompi4py()
        todo = gm.bcast([m for m in mine if not self.member_done(st, m)] if gm.Get_rank() == 0
                        else None, root=0)
        label = f"{st.kind}{' ' + st.matrix if st.matrix else ''} {st.system.name}"
        if len(todo) < len(mine):
            self.progress(f"{label}: {len(mine) - len(todo)} member(s) of this rank's group "
                          f"already done")
        if gm.Get_rank() == 0:
            os.makedirs(self.stage_dir(st), exist_ok=True)
        gm.Barrier()
        for m in todo:
            if self.stop_after is not None and self.computed >= self.stop_after:
                return True
            t0 = time.time()
            self.compute_member(st, m, comm)
            self.computed += 1
            self.counts[st.kind] += 1
            if gm.Get_rank() == 0:
                self.log(st, m)
            self.progress(f"{label}: member {m + 1}/{self.scene.members} in "
                          f"{time.time() - t0:.1f} s")
        return False

    def compute_member(self, st, m, comm):
        from parjam import io

        if st.kind == "pack":
            from parjam.ensemble import pack_member

            from parjam.errors import UnjammedError

            COUNTERS["pack"] += 1
            args = pack_args(self.scene, st.system, self.stage_dir(st))
            sub = self.progress.sub(f"pack {st.system.name} member {m + 1}: ")
            sub.enabled = False  # the bisection's lines would drown the stage progress
            try:
                pack_member(args, m, comm, sub)
            except UnjammedError as exc:  # rare: the member is left out, the ensemble goes on
                if comm.getRank() == 0:
                    with open(self.failed_path(st.system, m), "w") as fh:
                        fh.write(f"{exc}\n")
                    print(f"parjam: warning: {st.system.name} member {m}: {exc}; left out",
                          file=sys.stderr, flush=True)
            return
        data = {}
        for label in st.states:
            pack = io.read_packing(self.pack_path(st.system, m, label))
            try:
                data[label] = self.state_record(st, comm, pack, label)
            except ParjamError as exc:
                # e.g. a ladder state left with fewer contacts than isostatic (floppy modes):
                # raised by this member's group only, so record it and go on (raising it would
                # leave the other groups waiting for this one)
                data[label] = {"failed": str(exc)}
                if comm.getRank() == 0:
                    print(f"parjam: warning: {st.kind} {st.system.name} member {m} {label}: "
                          f"{exc}; recorded as missing", file=sys.stderr, flush=True)
        if comm.getRank() == 0:
            write_part(self.part_path(st, m), data,
                       {"stage": st.name, "member": m, "kind": st.kind})

    def state_record(self, st, comm, pack, label):
        if st.kind == "network":
            return network_record(pack)
        if st.kind == "spectrum":
            return spectrum_record(comm, pack, st.matrix, st.params[label],
                                   self.scene.solver["tol"])
        if st.kind == "moduli":
            return moduli_record(comm, pack)
        if st.kind == "softmodes":
            return softmodes_record(comm, pack, st.params)
        if st.kind == "fluctuations":
            COUNTERS["fluctuations"] += 1
            return contact_fluctuations(pack, st.params["max_divisions"])
        raise ValueError(f"unknown stage kind {st.kind}")

    # the summary -------------------------------------------------------------
    def summarise(self, st):
        """Ensemble tables of one system (world rank 0), skipped when already written."""
        path = self.summary_path(st)
        self.summaries[st.system.name] = path
        if self.mpi.Get_rank() == 0 and not os.path.isfile(path):
            COUNTERS["summary"] += 1
            by_kind = {}
            for dep in self.stages:
                if dep.key in st.deps and dep.kind != "pack":
                    tag = dep.kind + (f"/{dep.matrix}" if dep.matrix else "")
                    by_kind[tag] = [read_part(self.part_path(dep, m))
                                    for m in range(self.scene.members)
                                    if not self.failed(st.system, m)]
            failed = [m for m in range(self.scene.members) if self.failed(st.system, m)]
            write_summary(path, st, by_kind, self.scene, failed)
            with open(os.path.join(self.out, "stage.log"), "a") as fh:
                fh.write(f"{time.strftime('%Y-%m-%dT%H:%M:%S')} computed {st.name}\n")
        self.mpi.Barrier()

    def report(self):
        lines = [f"scene {self.scene.name}: results in {self.out}"]
        for name, path in self.summaries.items():
            lines.append(summary_table(path))
        return "\n".join(lines)

    def pictures(self):
        fig_dir = os.path.join(self.out, "figures")
        os.makedirs(fig_dir, exist_ok=True)
        dpi = self.scene.observables["pictures"]["dpi"]
        for name, path in self.summaries.items():
            dos_pictures(path, os.path.join(fig_dir, name), dpi)


def _lor():
    from mpi4py import MPI

    return MPI.LOR


# --------------------------------------------------------------------------- ensemble summary

SCALARS = {"network": ("phi", "phi_c", "z", "dz", "dz_iso", "pressure", "N_active", "excess",
                       "energy_per_particle", "max_force", "stable"),
           "spectrum": ("D0", "omega_star", "omega_min", "n_negative"),
           "moduli": ("B", "G", "G_min", "B_affine", "G_affine"),
           "softmodes": ("c", "c_nontrivial", "q", "q_prime_over_q", "omega_L2", "omega_t2",
                         "trial_energy_max", "count", "expected", "L")}


def ensemble_dos(records, bins, log=False, omega_min=None):
    """D(omega) per mode of each member on common bins up to the lowest of the members' top
    frequencies (parjam.observables), averaged with standard errors."""
    from parjam import observables

    omegas = [r["frequency"][r["frequency"] > 0] for r in records]
    top = min(float(w.max()) for w in omegas)
    lo = omega_min
    edges = observables.dos_edges(top, bins, log, lo)
    dens = []
    for r, w in zip(records, omegas):
        centres, dn = observables.density_of_states(w, int(r["n_modes_total"]), edges)
        dens.append(dn)
    mean, err = observables.ensemble_mean(dens)
    return centres, edges, mean, err


def write_summary(path, st, by_kind, scene, failed=()):
    """/<state>/<kind>/<quantity>: per-member values (axis 0 = member), mean and error, and for
    spectra the ensemble D(omega) and the pooled per-mode sums."""
    from parjam import io, observables

    obs = scene.observables
    dos_opts = obs.get("dos", {"bins": 40, "log_bins": False, "omega_min": None})
    with io.atomic_h5(path) as f:
        io.write_h5md_header(f, io.provenance(1, {"command": "run", "scene": scene.path}))
        f.attrs["system"] = st.system.name
        for k, v in st.system.key().items():
            f.attrs[k] = v
        f.attrs["members"] = scene.members - len(failed)
        f.attrs["failed_members"] = np.array(list(failed), dtype=np.int64)
        f.attrs["states"] = np.array([s.encode() for s in st.states])
        for tag, parts in by_kind.items():
            kind = tag.split("/")[0]
            for label in st.states:
                every = [p.get(label, {"failed": "not computed"}) for p in parts]
                every = [{"failed": r["error"]} if isinstance(r.get("error"), str) else r
                         for r in every]  # the failure key of earlier versions
                recs = [r for r in every if "failed" not in r]
                if not recs:
                    continue
                g = f.require_group(f"{label}/{tag}")
                # per-member scalars keep one entry per member (NaN where it failed)
                for q in SCALARS.get(kind, ()):
                    vals = np.array([float(r.get(q, np.nan)) for r in every])
                    ds = g.create_dataset(q, data=vals)
                    with warnings.catch_warnings():  # a single finite member: error nan
                        warnings.simplefilter("ignore", RuntimeWarning)
                        mean, err = observables.ensemble_mean(vals[:, None])
                    ds.attrs["mean"], ds.attrs["error"] = float(mean[0]), float(err[0])
                failed = [k for k, r in enumerate(every) if "failed" in r]
                if failed:
                    g.attrs["failed_members"] = np.array(failed, dtype=np.int64)
                    g.attrs["errors"] = "; ".join(every[k]["failed"] for k in failed)
                if kind == "spectrum":
                    ids = [k for k, r in enumerate(every) if "failed" not in r]
                    _spectrum_summary(g, recs, ids, dos_opts)
                elif kind == "softmodes":
                    g.create_dataset("overlap", data=np.array([r["overlap"] for r in recs]))
                    g.create_dataset("trial_energy",
                                     data=np.concatenate([r["trial_energy"] for r in recs]))
                    g.create_dataset("extension",
                                     data=np.concatenate([r["extension"] for r in recs]))
                elif kind == "fluctuations":
                    for q in ("l", "var_contacts", "var_excess", "mean_particles",
                              "mean_contacts"):
                        g.create_dataset(q, data=np.array([r[q] for r in recs]))


def _spectrum_summary(g, recs, ids, opts):
    if all(np.any(r["frequency"] > 0) for r in recs):
        centres, edges, mean, err = ensemble_dos(recs, opts["bins"], opts["log_bins"],
                                                 opts["omega_min"])
        d = g.create_group("dos")
        for name, val in (("omega", centres), ("edges", edges), ("density", mean),
                          ("density_error", err)):
            d.create_dataset(name, data=val)
    freq = np.concatenate([r["frequency"] for r in recs])
    g.create_dataset("frequency", data=freq)
    g.create_dataset("member_of_mode", data=np.concatenate(
        [np.full(len(r["frequency"]), k) for k, r in zip(ids, recs)]))
    if all("eps_perp" in r for r in recs):
        for q in ("eps_perp", "eps_par", "participation_ratio"):
            g.create_dataset(q, data=np.concatenate([r[q] for r in recs]))
    g.create_dataset("lowest_frequency", data=np.array(
        [np.min(r["frequency"][r["frequency"] > 0]) if np.any(r["frequency"] > 0) else np.nan
         for r in recs]))


def read_summary(path):
    """A summary file as nested dicts: {state: {kind: {quantity: array}}} plus attrs."""
    import h5py

    def walk(g):
        return {k: (walk(v) if isinstance(v, h5py.Group) else v[()]) for k, v in g.items()}

    with h5py.File(path, "r") as f:
        out = {k: walk(v) for k, v in f.items() if k != "h5md"}
        out["attrs"] = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
    return out


def summary_table(path):
    """One line per state: ensemble means of dz (from the isostatic count), p and the spectra's
    omega*."""
    s = read_summary(path)
    lines = [f"{s['attrs']['system']} ({s['attrs']['members']} members): {os.path.basename(path)}"]
    for label in [x.decode() for x in s["attrs"]["states"]]:
        if label not in s:
            continue
        parts = [f"  {label:>12}"]
        net = s[label].get("network", {})
        for q, name in (("dz_iso", "dz"), ("pressure", "p")):
            if q in net:
                parts.append(f"{name} {np.nanmean(net[q]):.4g}")
        if "stable" in net and np.any(net["stable"] == 0):
            parts.append(f"UNSTABLE {int(np.sum(net['stable'] == 0))} member(s)")
        for kind, val in sorted(s[label].get("spectrum", {}).items()):
            if "omega_star" in val:
                parts.append(f"omega*({kind}) {np.nanmean(val['omega_star']):.4g}")
        lines.append("  ".join(parts))
    return "\n".join(lines)


def dos_pictures(path, stem, dpi):
    """D(omega) of every matrix, the states overlaid (log-linear, as the paper's figures)."""
    from parjam.plot import pyplot

    s = read_summary(path)
    states = [x.decode() for x in s["attrs"]["states"]]
    kinds = sorted({k for lab in states if lab in s for k in s[lab].get("spectrum", {})})
    plt = pyplot()
    for kind in kinds:
        fig, ax = plt.subplots(figsize=(5, 3.6))
        for lab in states:
            dos = s.get(lab, {}).get("spectrum", {}).get(kind, {}).get("dos")
            if dos is not None:
                ax.errorbar(dos["omega"], dos["density"], yerr=dos["density_error"], fmt="-",
                            lw=1, label=lab)
        ax.set(xlabel=r"$\omega$", ylabel=r"$D(\omega)$ per mode",
               title=f"{s['attrs']['system']}: {kind}")
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(f"{stem}-dos-{kind}.png", dpi=dpi)
        plt.close(fig)
