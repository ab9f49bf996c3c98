#!/usr/bin/env python3
"""KPM against dense LAPACK on packing states (docs/reproduction.md, section 11): what the
N = 10240 scene `scenes/paper-3d-10x-spectra.toml` measures by KPM and by partial spectra,
checked where the whole spectrum is affordable.

    nice .venv/bin/python scripts/check_kpm_dense.py PACKS/member*_dphi*.h5 \
        --moments 2048 --probes 8 --k-fraction 0.033 --json out.json --md table.md

For each state and matrix (full, relaxed): the dense eigenvalues (the truth), then with the
scene's KPM settings (parjam.vib.kpm_dos, the same code as ``parjam run``):
- L1 distance of the per-mode D(omega) on 40 bins, and the relative error of D0;
- omega* of KPM (NaN when parjam.vib.kpm_dos calls it unresolved) against dense;
- omega* of the lowest ``k-fraction`` of the modes with the KPM D0 (the partial-spectrum
  estimator of omega_AM and omega*_relaxed at N = 10240) against dense.
Serial, one process; nothing is written but --json and --md.
"""

import argparse
import json
import os
import sys

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from parjam import env
from parjam.files import h5md
from parjam.vib import kpm, kpm_dos, observables, spectrum


def dense_frequencies(system, kind):
    H = spectrum.dense_matrix(system, kind)
    lam = np.linalg.eigvalsh(H)[system.d:]  # the d translations are the lowest (exact zeros)
    return observables.frequency(lam)


def check(path, kind, moments, probes, max_moments, k_fraction, bins=40):
    comm = env.petsc().COMM_SELF
    system = spectrum.active_system(h5md.read_packing(path))
    w = dense_frequencies(system, kind)
    pos = w[w > 0]
    d0, wstar, _ = observables.dos_summary(pos, system.n_modes)
    res = kpm_dos.compute(comm, system, kind, moments, probes, max_moments)
    kd0, kstar, kraw, _ = kpm_dos.summary(res)
    edges = observables.dos_edges(min(res.omega_max, pos.max() * 1.001), bins)
    _, dense_density = observables.density_of_states(pos, system.n_modes, edges)
    l1 = kpm.l1_distance(res.binned(edges), dense_density, edges)
    k = int(round(k_fraction * system.n_modes))
    partial = observables.omega_star(pos[:k], system.n_modes, kd0)
    return {"file": os.path.basename(path), "matrix": kind, "n_modes": system.n_modes,
            "moments": res.n_moments, "probes": probes, "seconds": res.seconds,
            "L1": l1, "D0_dense": d0, "D0_kpm": kd0, "omega_star_dense": wstar,
            "omega_star_kpm": kstar, "omega_star_kpm_raw": kraw,
            "resolution": kpm_dos.resolution(res.b, res.n_moments), "k": k,
            "omega_star_partial": partial, "omega_top_partial": float(pos[k - 1])}


def calibrate(path, kind, probes, grid=(256, 512, 1024, 2048, 4096, 8192)):
    """KPM omega* at fixed moments against dense: the ratio omega*_KPM / Delta omega and the
    relative error, the data behind parjam.vib.kpm_dos.RESOLVED."""
    comm = env.petsc().COMM_SELF
    system = spectrum.active_system(h5md.read_packing(path))
    w = dense_frequencies(system, kind)
    _, wstar, _ = observables.dos_summary(w[w > 0], system.n_modes)
    out = []
    for m in grid:
        res = kpm_dos.compute(comm, system, kind, m, probes, m)
        _, _, raw, _ = kpm_dos.summary(res)
        dw = kpm_dos.resolution(res.b, m)
        out.append({"file": os.path.basename(path), "matrix": kind, "moments": m,
                    "ratio": raw / dw, "rel_error": raw / wstar - 1.0,
                    "omega_star_dense": wstar})
        print(json.dumps(out[-1]), flush=True)
    return out


def calibration_table(rows):
    ms = sorted({r["moments"] for r in rows})
    out = ["| state | matrix | omega* dense | " + " | ".join(f"M = {m}" for m in ms) + " |",
           "|---|---|---|" + "---|" * len(ms)]
    keys = list(dict.fromkeys((r["file"], r["matrix"]) for r in rows))
    for f, kind in keys:
        sel = {r["moments"]: r for r in rows if r["file"] == f and r["matrix"] == kind}
        first = next(iter(sel.values()))
        cells = [f"{100 * sel[m]['rel_error']:+.0f} % ({sel[m]['ratio']:.1f})" for m in ms]
        out.append(f"| {f.replace('.h5', '')} | {kind} | {first['omega_star_dense']:.4f} | "
                   + " | ".join(cells) + " |")
    return "\n".join(out)


def fmt(x, spec=".4f"):
    return "NaN" if not np.isfinite(x) else format(x, spec)


def table(rows):
    out = ["| state | matrix | moments | L1 | D0 dense | D0 KPM | omega* dense | omega* KPM "
           "(raw) | omega* lowest k + KPM D0 (k) |",
           "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(
            f"| {r['file'].replace('.h5', '')} | {r['matrix']} | {r['moments']} | "
            f"{r['L1']:.3f} | {r['D0_dense']:.4f} | {r['D0_kpm']:.4f} "
            f"| {fmt(r['omega_star_dense'])} | {fmt(r['omega_star_kpm'])} "
            f"({fmt(r['omega_star_kpm_raw'])}) | {fmt(r['omega_star_partial'])} ({r['k']}) |")
    return "\n".join(out)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("packings", nargs="+")
    p.add_argument("--moments", default="auto")
    p.add_argument("--probes", type=int, default=8)
    p.add_argument("--max-moments", type=int, default=4096)
    p.add_argument("--k-fraction", type=float, default=0.033)
    p.add_argument("--matrices", default="full,relaxed")
    p.add_argument("--calibrate", action="store_true",
                   help="KPM omega* error against omega*_KPM / Delta omega at 256 .. 8192 "
                        "moments instead")
    p.add_argument("--json")
    p.add_argument("--md")
    a = p.parse_args(argv)
    moments = a.moments if a.moments == "auto" else int(a.moments)
    rows = []
    for path in a.packings:
        for kind in a.matrices.split(","):
            if a.calibrate:
                rows += calibrate(path, kind, a.probes)
                continue
            rows.append(check(path, kind, moments, a.probes, a.max_moments, a.k_fraction))
            print(json.dumps(rows[-1]), flush=True)
    text = calibration_table(rows) if a.calibrate else table(rows)
    print(text)
    if a.md:
        with open(a.md, "w") as fh:
            fh.write(text + "\n")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(rows, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
