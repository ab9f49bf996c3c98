"""The per-state work of a scene's analysis stages: one record (a dict of arrays and scalars) per
packing state, computed by the physics modules on the distributed active network of the
state's file (parjam.files.rowio: each rank reads its rows, no rank holds all N).  The records are
written by rank 0; a scene that stores eigenvectors (``lowest.vectors``) has them gathered
there, in particle-id order."""

import numpy as np

from parjam.net import active
from parjam.vib import dense, kpm, kpm_dos, moduli, observables, spectrum
from parjam import softmodes as sm
from parjam.errors import ParjamError


def network_record(comm, rows, net=None):
    """z, dz, p and the rest of the contact-network summary of a state's file rows (``rows``,
    rowio.read_rows; parjam.net.active)."""
    net = net if net is not None else active.from_rows(comm, rows)
    rec = dict(net.summary())
    rec["phi_c"] = float(rows.meta.get("phi_c", np.nan))
    # 1 for a stable minimum, 0 for a state the packing protocol could not make one (flagged,
    # kept: parjam.pack.packing.Jammer.stabilise); NaN for files written before the check existed
    rec["stable"] = float(rows.meta.get("stable", np.nan))
    return rec


def dense_eigenvalues(comm, system, kind):
    """All eigenvalues of one matrix without eigenvectors (LAPACK eigvalsh of the deflated dense
    matrix, parjam.vib.spectrum's dense reference without its vectors): rank 0 computes, all get
    (the system is gathered there first: the dense path is for small N)."""
    mpi = comm.tompi4py()
    res = None
    whole = system.gathered(comm)
    if mpi.Get_rank() == 0:
        H = dense.dense_matrix(whole, kind)
        norm = float(np.abs(H).sum(axis=1).max())
        lam, _ = dense.dense_eigh(dense.deflated_dense(H, whole.n, whole.d, norm),
                                  k=whole.n_modes, vectors=False)
        res = (lam, norm)
    return mpi.bcast(res, root=0)


def spectrum_record(comm, rows, kind, req, tol):
    """The spectrum a state needs (req from parjam.study.plan.spectrum_needs, with its solver), with
    D0 and omega* (parjam.vib.observables) and the per-mode sums when they were computed."""
    system = spectrum.distributed_system(active.from_rows(comm, rows))
    sol = req["solver"]
    rec = {"solver": sol, "n_modes_total": system.n_modes, "n_active": system.n}
    if req.get("kpm"):  # D(omega) by KPM (dos = { method = "kpm" }): the moments are stored
        o = req["kpm"]
        rec.update(kpm_dos.to_record(kpm_dos.compute(comm, system, kind, o["moments"],
                                                     o["probes"], o["max_moments"])))
    if sol == "kpm":
        rec.update(eigenvalue=np.zeros(0), frequency=np.zeros(0), D0=rec["kpm_D0"],
                   omega_star=rec["omega_star_kpm_resolved"],
                   plateau_window=rec["kpm_window"], omega_min=np.nan, n_negative=np.nan,
                   pressure=system.pressure, complete=False, plateau_source="kpm")
        return rec
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
        if req["vectors"]:
            parts = [spectrum.vectors_on_root(comm, s) for s in specs]  # collective
            if comm.getRank() == 0:
                rec["eigenvector"] = np.concatenate(parts)[first]
        if req["window"] is not None and sol == "dense-eigh":  # the dense path computed all
            rec["window"] = np.array(req["window"], dtype=float)
    omega = observables.frequency(rec["eigenvalue"])
    rec["frequency"] = omega
    pos = omega[omega > 0]
    if req.get("kpm") and not sol.startswith("dense"):  # a partial spectrum with KPM D0
        d0, window = rec["kpm_D0"], rec["kpm_window"]
        wstar = observables.omega_star(pos, system.n_modes, d0)
        rec["plateau_source"] = "kpm"
    elif req.get("kpm_plateau") and not sol.startswith("dense"):  # a partial spectrum
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
    plateau D0 from KPM moments of the whole matrix (parjam.vib.kpm, the 30-60 % frequency
    quantiles), omega* from the computed modes with it (parjam.vib.observables.omega_star: N(omega)
    is exact up to the highest computed mode; NaN if the modes do not reach 2 omega*).  The
    partial spectrum's own upper half would bias D0, and omega* with it, low: by 5-20 % at
    dphi = 1e-5 .. 1e-3 (3D, N = 1024, docs/results/reproduction.md)."""
    res = kpm.compute(comm, system, kind, **KPM_PLATEAU)
    d0, _, window = kpm.dos_summary(res)
    return d0, observables.omega_star(omega, system.n_modes, d0), window


def moduli_record(comm, rows):
    mod = moduli.compute(comm=comm, net=active.from_rows(comm, rows))
    rec = {k: v for k, v in mod.summary().items() if v is not None and np.isscalar(v)}
    rec["stiffness"] = mod.stiffness
    return rec


def softmodes_record(comm, rows, opts):
    planes = [sm.parse_cut(c, rows.d) for c in opts["cuts"]]
    if opts["subdivide"] is not None:
        planes += sm.subdivision_planes(opts["subdivide"], rows.d)
    cs = sm.prepare(None, list(dict.fromkeys(planes)), opts["allow_hyperstatic"],
                    net=active.from_rows(comm, rows))
    res = sm.analyze(comm, cs, opts["e0"], opts["bins"])
    rec = {k: (np.nan if v is None else v) for k, v in res.summary().items()}
    rec.update(overlap=res.overlap, extension=res.e, trial_energy=res.trial_energy,
               extended_fraction=res.fractions, L=cs.L, n_planes=len(cs.planes))
    return rec
