#!/usr/bin/env python3
"""Elastic moduli, sound speeds and lengths over a dphi ladder for an ensemble, with fitted
exponents and bootstrap errors over members.  Run by hand (results in docs/results/moduli-lengths.md):

    nice -n 10 .venv/bin/python scripts/moduli_scaling.py --dim 3 --n 256 --members 8 \
        --dphi 1e-4 1e-3 1e-2 1e-1 [--alpha 2] [--lengths] --out bench-out/scaling_d3.json
    # or existing packing files (one member per directory, any dphi), with l* as well:
    nice -n 10 .venv/bin/python scripts/moduli_scaling.py --files DIR/member*_dphi*.h5 \
        --lengths --lstar --out bench-out/lengths_d3.json

Packings are made with parjam.pack.packing.make_jammed (seed, member as in ``parjam pack``); under
mpirun the members are spread over the ranks (each on COMM_SELF).  Expected (O'Hern et al.
2003; Wyart et al. 2005): B ~ dphi^(alpha-2), G ~ dphi^(alpha-3/2), G/B ~ dphi^(1/2), and in
dz: omega* ~ dz, c_T ~ dz^(alpha-3/2) (dz ~ dphi^(1/2)), l_T ~ c_T/omega*, l_L ~ 1/dz,
l* ~ 1/dz.  Packings with a negative shear modulus in some direction (G_min < 0) are counted per
dphi and fitted both with and without them.
"""

import argparse
import json
import os
import re
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)


def record(pack, comm, lengths_too, lstar_too, extra):
    from parjam import lengths
    from parjam.vib import moduli
    from parjam.net.network import analyze

    net = analyze(pack)
    mod = moduli.compute(pack, comm)
    s = mod.summary()
    row = dict(extra, d=pack.d, n=pack.n, alpha=pack.alpha, phi=pack.phi, p=s["pressure"],
               z=net.z, dz=net.dz, N_active=net.n_active, B=s["B"], G=s["G"], G_min=s["G_min"],
               B_affine=s["B_affine"], G_affine=s["G_affine"], max_residual=s["max_residual"])
    rho = lengths.mass_density(net.n_active, pack.volume)
    row["rho"] = rho
    row["c_L"], row["c_T"] = lengths.sound_speeds(s["B"], s["G"], pack.d, rho)
    what = (["omega"] if lengths_too else []) + (["lstar"] if lstar_too else [])
    if what:
        res = lengths.compute(comm, pack, what, method="dense",
                              ells=np.geomspace(2.0, pack.L, 14), samples=8)
        row.update({k: v for k, v in res.summary().items()
                    if k in ("omega_star", "D0", "lstar", "lstar_estimate", "lstar_soft",
                             "lstar_extended")})
        if res.dos is not None:
            row["l_L"], row["l_T"] = lengths.acoustic_lengths(row["c_L"], row["c_T"],
                                                              res.omega_star)
    return row


def ensemble(args, comm_world):
    from parjam import env
    from parjam.errors import UnjammedError
    from parjam.pack.packing import make_jammed

    SELF = env.petsc().COMM_SELF
    rank, size = comm_world.Get_rank(), comm_world.Get_size()
    rows = []
    for member in range(args.members):
        if member % size != rank:
            continue
        t0 = time.perf_counter()
        try:
            _, ladder = make_jammed(args.dim, args.n, args.dphi, seed=args.seed, member=member,
                                    alpha=args.alpha, comm=SELF)
        except UnjammedError as exc:  # reported in the JSON, not silently dropped
            rows.append({"member": member, "failed": str(exc)})
            print(f"[rank {rank}] member {member}: {exc}", flush=True)
            continue
        for dphi, pack in zip(args.dphi, ladder):
            rows.append(record(pack, SELF, args.lengths, args.lstar,
                               {"member": member, "dphi": dphi}))
        print(f"[rank {rank}] member {member}: {time.perf_counter() - t0:.1f} s", flush=True)
    return sum(comm_world.allgather(rows), [])


def from_files(args, comm_world):
    from parjam import env
    from parjam.files import h5md

    SELF = env.petsc().COMM_SELF
    rank, size = comm_world.Get_rank(), comm_world.Get_size()
    rows = []
    for k, path in enumerate(sorted(args.files)):
        if k % size != rank:
            continue
        pack = h5md.read_packing(path)
        m = re.search(r"dphi([0-9.e+-]+)\.h5$", path)
        dphi = float(m.group(1)) if m else float("nan")
        member = os.path.dirname(os.path.abspath(path))
        rows.append(record(pack, SELF, args.lengths, args.lstar,
                           {"member": member, "dphi": dphi, "file": path}))
        print(f"[rank {rank}] {path} done", flush=True)
    return sum(comm_world.allgather(rows), [])


# --------------------------------------------------------------------------- analysis

def table(rows, key, xs, members):
    """members x len(xs) array of ``key`` (NaN where missing)."""
    Y = np.full((len(members), len(xs)), np.nan)
    for r in rows:
        if key in r and r[key] is not None:
            Y[members.index(r["member"]), xs.index(r["dphi"])] = r[key]
    return Y


def power_law_fit(x, Y):
    """(exponent, bootstrap error) of mean(Y) ~ x^s over members (parjam.study.fits.fit_power)."""
    from parjam.study.fits import fit_power

    f = fit_power(x, Y)
    return f["exponent"], f["exponent_err"]


def fits(rows, gfit_min):
    xs = sorted({r["dphi"] for r in rows})
    members = sorted({r["member"] for r in rows}, key=str)
    alpha = rows[0]["alpha"]
    B, G, Gmin = (table(rows, k, xs, members) for k in ("B", "G", "G_min"))
    stable = Gmin > 0
    gx = [x for x in xs if x >= gfit_min]
    gi = [xs.index(x) for x in gx]
    out = {"dphi": xs, "members": len(members), "alpha": alpha,
           "unstable_per_dphi": [int((~stable[:, k]).sum()) for k in range(len(xs))],
           "expected": {"B": alpha - 2, "G": alpha - 1.5, "G/B": 0.5}, "G_fit_from": gfit_min}
    ratio = G / B
    for label, mask in (("all", np.ones_like(stable)), ("stable", stable)):
        Bm, Gm, Rm = (np.where(mask, Y, np.nan) for Y in (B, G, ratio))
        out[label] = {
            "B": power_law_fit(xs, Bm), "G": power_law_fit(gx, Gm[:, gi]),
            "G/B": power_law_fit(gx, Rm[:, gi]),
            "B_mean": np.nanmean(Bm, axis=0).tolist(), "G_mean": np.nanmean(Gm, axis=0).tolist(),
            "G_sem": (np.nanstd(Gm, axis=0, ddof=1)
                      / np.sqrt(np.maximum(np.isfinite(Gm).sum(axis=0), 1))).tolist(),
            "B_sem": (np.nanstd(Bm, axis=0, ddof=1)
                      / np.sqrt(np.maximum(np.isfinite(Bm).sum(axis=0), 1))).tolist(),
        }
    dz = table(rows, "dz", xs, members)
    out["dz_mean"] = np.nanmean(dz, axis=0).tolist()
    out["p_mean"] = np.nanmean(table(rows, "p", xs, members), axis=0).tolist()
    for key in ("omega_star", "c_T", "c_L", "l_T", "l_L", "lstar", "lstar_extended",
                "lstar_estimate"):
        Y = table(rows, key, xs, members)
        if np.isfinite(Y).any():
            out[key + "_mean"] = np.nanmean(Y, axis=0).tolist()
            ok = (np.isfinite(Y).all(axis=0) & (np.nanmean(Y, axis=0) > 0)
                  & (np.array(out["dz_mean"]) > 0))
            if ok.sum() >= 2:
                # exponent against the member-mean dz at each dphi
                lx = np.log(np.array(out["dz_mean"])[ok])
                out[key + "_vs_dz"] = float(np.polyfit(lx, np.log(np.nanmean(Y, axis=0)[ok]),
                                                       1)[0])
    return out


def report(f):
    lines = [f"alpha = {f['alpha']}, {f['members']} members, dphi = {f['dphi']}",
             f"members with G_min < 0 per dphi: {f['unstable_per_dphi']}"]
    for label in ("all", "stable"):
        g = f[label]
        lines.append(
            f"  {label:6s}: B exponent {g['B'][0]:.3f} +- {g['B'][1]:.3f} (expected "
            f"{f['expected']['B']}), G {g['G'][0]:.3f} +- {g['G'][1]:.3f} (expected "
            f"{f['expected']['G']}, dphi >= {f['G_fit_from']:g}), G/B {g['G/B'][0]:.3f} +- "
            f"{g['G/B'][1]:.3f} (expected 0.5)")
        lines.append("          B: " + " ".join(f"{m:.4f}+-{e:.4f}" for m, e in
                                                zip(g["B_mean"], g["B_sem"])))
        lines.append("          G: " + " ".join(f"{m:.4f}+-{e:.4f}" for m, e in
                                                zip(g["G_mean"], g["G_sem"])))
    lines.append("  dz: " + " ".join(f"{x:.4f}" for x in f["dz_mean"]))
    for key in ("omega_star", "c_T", "c_L", "l_T", "l_L", "lstar", "lstar_extended",
                "lstar_estimate"):
        if key + "_mean" in f:
            lines.append(f"  {key}: " + " ".join(f"{x:.4g}" for x in f[key + "_mean"])
                         + (f"   exponent vs dz {f[key + '_vs_dz']:.3f}"
                            if key + "_vs_dz" in f else ""))
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dim", type=int, default=3)
    ap.add_argument("--n", type=int, default=256)
    ap.add_argument("--members", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--alpha", type=float, default=2.0)
    ap.add_argument("--dphi", type=float, nargs="+", default=[1e-4, 1e-3, 1e-2, 1e-1])
    ap.add_argument("--files", nargs="+", help="existing packings instead of an ensemble")
    ap.add_argument("--lengths", action="store_true", help="also omega*, l_L, l_T (dense)")
    ap.add_argument("--lstar", action="store_true", help="also l* from cut cubes")
    ap.add_argument("--gfit-min", type=float, default=1e-3,
                    help="smallest dphi of the G and G/B fits (default 1e-3)")
    ap.add_argument("--out", required=True, help="JSON with every row and the fits")
    args = ap.parse_args()
    import warnings

    warnings.simplefilter("ignore", RuntimeWarning)  # means over all-NaN (all-unstable) columns
    from parjam import env

    env.init()
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    t0 = time.perf_counter()
    rows = from_files(args, comm) if args.files else ensemble(args, comm)
    failed = [r for r in rows if "failed" in r]
    rows = [r for r in rows if "failed" not in r]
    if comm.Get_rank() == 0:
        with open(args.out, "w") as fh:  # the rows first: a failing fit loses nothing
            json.dump({"rows": rows, "failed": failed, "args": vars(args)}, fh, default=float)
        f = fits(rows, args.gfit_min)
        f["failed_members"] = failed
        for r in failed:
            print(f"member {r['member']} left out: {r['failed']}")
        with open(args.out, "w") as fh:
            json.dump({"rows": rows, "fits": f, "failed": failed, "args": vars(args),
                       "seconds": time.perf_counter() - t0}, fh, default=float)
        if f:
            print(report(f))
        print(f"written {args.out} ({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
