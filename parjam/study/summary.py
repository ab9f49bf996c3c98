"""The summary file of a scene (one per system): written by the runner, read by the plots."""

import os
import warnings

import h5py
import numpy as np

from parjam.files import h5md
from parjam.vib import kpm_dos, observables

# --------------------------------------------------------------------------- ensemble summary

SCALARS = {"network": ("phi", "phi_c", "z", "dz", "dz_iso", "pressure", "N_active", "excess",
                       "energy_per_particle", "max_force", "stable"),
           "spectrum": ("D0", "omega_star", "omega_min", "n_negative"),
           "moduli": ("B", "G", "G_min", "B_affine", "G_affine"),
           "softmodes": ("c", "c_nontrivial", "q", "q_prime_over_q", "omega_L2", "omega_t2",
                         "trial_energy_max", "count", "expected", "L")}


def ensemble_dos(records, bins, log=False, omega_min=None):
    """D(omega) per mode of each member on common bins up to the lowest of the members' top
    frequencies (parjam.vib.observables), averaged with standard errors."""
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
    obs = scene.observables
    dos_opts = obs.get("dos", {"bins": 40, "log_bins": False, "omega_min": None})
    with h5md.atomic_h5(path) as f:
        h5md.write_h5md_header(f, h5md.provenance(1, {"command": "run", "scene": scene.path}))
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
                    if all("kpm_moments" in r for r in recs):
                        _kpm_summary(g, every, recs, tag.split("/")[1], dos_opts)
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


KPM_SCALARS = ("kpm_D0", "kpm_omega_star", "kpm_resolved", "kpm_n_moments", "kpm_resolution",
               "kpm_seconds")


def kpm_ensemble_dos(records, matrix, bins, log=False, omega_min=None):
    """D(omega) per mode of each member from its stored KPM moments (parjam.vib.kpm_dos) on common
    bins up to the lowest of the members' spectral bounds sqrt(b), averaged over the members.
    Returns centres, edges, mean, its standard error over the members, the probes' stochastic
    error of the mean (sqrt(sum err_m^2) / members) and their quadrature sum."""
    res = [kpm_dos.from_record(r, matrix) for r in records]
    edges = observables.dos_edges(min(x.omega_max for x in res), bins, log, omega_min)
    dens, errs = zip(*(x.binned_with_error(edges) for x in res))
    mean, err_members = observables.ensemble_mean(list(dens))
    err_probes = np.sqrt(np.sum(np.square(errs), axis=0)) / len(res)
    err_members = np.nan_to_num(err_members)  # one member: no scatter, the probes' error only
    return (0.5 * (edges[1:] + edges[:-1]), edges, mean, err_members, err_probes,
            np.hypot(err_members, err_probes))


def _kpm_summary(g, every, recs, matrix, opts):
    """The KPM scalars per member (NaN where missing) and the ensemble D(omega) from the KPM
    moments: this "dos" group replaces the partial spectrum's histogram (a partial spectrum
    has no whole D(omega)); ``kpm_moments`` in it marks the source."""
    for q in KPM_SCALARS:
        vals = np.array([float(r.get(q, np.nan)) for r in every])
        ds = g.create_dataset(q, data=vals)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            mean, err = observables.ensemble_mean(vals[:, None])
        ds.attrs["mean"], ds.attrs["error"] = float(mean[0]), float(err[0])
    centres, edges, mean, e_m, e_p, err = kpm_ensemble_dos(
        recs, matrix, opts["bins"], opts["log_bins"], opts["omega_min"])
    if "dos" in g:
        del g["dos"]
    d = g.create_group("dos")
    for name, val in (("omega", centres), ("edges", edges), ("density", mean),
                      ("density_error", err), ("density_error_members", e_m),
                      ("density_error_probes", e_p),
                      ("kpm_moments", np.array([int(r["kpm_n_moments"]) for r in recs]))):
        d.create_dataset(name, data=val)


def read_summary(path):
    """A summary file as nested dicts: {state: {kind: {quantity: array}}} plus attrs."""
    def walk(g):
        return {k: (walk(v) if isinstance(v, h5py.Group) else v[()]) for k, v in g.items()}

    with h5py.File(path, "r") as f:
        out = {k: walk(v) for k, v in f.items() if k != "h5md"}
        out["attrs"] = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
    return out


def summary_table(path):
    """One line per state: ensemble means of dz_iso = z - z_iso, p and the spectra's omega*."""
    s = read_summary(path)
    lines = [f"{s['attrs']['system']} ({s['attrs']['members']} members): {os.path.basename(path)}"]
    for label in [x.decode() for x in s["attrs"]["states"]]:
        if label not in s:
            continue
        parts = [f"  {label:>12}"]
        net = s[label].get("network", {})
        for q, name in (("dz_iso", "dz_iso"), ("pressure", "p")):
            if q in net:
                parts.append(f"{name} {np.nanmean(net[q]):.4g}")
        if "stable" in net and np.any(net["stable"] == 0):
            parts.append(f"UNSTABLE {int(np.sum(net['stable'] == 0))} member(s)")
        for kind, val in sorted(s[label].get("spectrum", {}).items()):
            if "omega_star" in val:
                parts.append(f"omega*({kind}) {np.nanmean(val['omega_star']):.4g}")
        lines.append("  ".join(parts))
    return "\n".join(lines)
