"""Figures of soft modes after cuts (2D packings): the paper's Fig. "softfig" (one soft mode drawn
as arrows after 20 contacts along a vertical line are cut) and Fig. "figs" (which contacts a cut
removes).  ``python -m parjam.plot.softmodes PACKING.h5 --out-dir DIR`` writes both PNGs."""

import argparse
import os
import sys

import h5py
import numpy as np

from parjam import env
from parjam.files import h5md
from parjam import softmodes as sm
from parjam.plot import DPI, LEGEND_FONTSIZE, pyplot
from parjam.plot.labels import describe, readable_log_ticks, title


def crossing_height(pos_i, rij, L, plane):
    """Where each bond x_i -> x_i + r_ij crossing ``plane`` meets it: the coordinate along the
    next axis."""
    a, b = plane.axis, (plane.axis + 1) % pos_i.shape[1]
    x0 = plane.frac * L
    xi = pos_i[:, a]
    image = x0 + L * np.floor((np.maximum(xi, xi + rij[:, a]) - x0) / L)
    t = (image - xi) / np.where(rij[:, a] == 0, np.inf, rij[:, a])
    return np.mod(pos_i[:, b] + t * rij[:, b], L)


def segment_cut(cs, plane, ncut):
    """The cut system of ``cs``'s network cutting only ``ncut`` consecutive contacts along
    ``plane`` (centred on the middle of the box): the paper's "contacts along a vertical line".
    Figures are serial: ``cs`` must live on one rank (sm.prepare's default, COMM_SELF)."""
    if cs.comm.Get_size() != 1:
        raise sm.ParjamError("segment_cut needs the cut system on one rank")
    c = cs.contacts
    on = sm.half_edge_masks(cs.net, [plane])[0] & (c.i < c.j)  # each contact once
    idx = np.flatnonzero(on)
    if len(idx) < ncut:
        raise sm.ParjamError(f"the plane {plane.label} crosses only {len(idx)} contacts, "
                             f"fewer than {ncut}")
    h = crossing_height(cs.pos[c.i[idx] - cs.lo], c.rij[idx], cs.L, plane)
    chosen = idx[np.argsort(np.abs(h - 0.5 * cs.L))][:ncut]
    key = np.minimum(c.i, c.j) * cs.n + np.maximum(c.i, c.j)
    mask = np.isin(key, key[chosen])  # both half-edges of every chosen contact
    return sm.cut_system(cs.net, [plane], mask, [ncut], cs.source)


def soft_space(comm, cs):
    """(count, local basis rows) of the null space of a cut system, translations excluded."""
    M = sm.relaxed_matrix(comm, cs, cs.kept)
    count = sm.null_count(comm, M, cs.scale)
    nb = sm.null_basis(comm, M, cs.d, count - cs.d, cs.scale)
    M.destroy()
    return count, nb.V


def most_extended(comm, cs, V):
    """The soft mode of largest extension e (the top eigenvector of G projected on the soft
    space, G = sin^2(pi x / L) from the cut line): basis independent, unlike any one column."""
    g = sm.modulation(cs.pos, cs.L, [sm.Plane(0, 0.5)])
    e, W = sm.extended_basis(comm, V, g**2)
    return W[:, -1], float(e[-1])


def _disks(ax, pos, diam, L, colors, lw=0.3):
    from matplotlib.collections import EllipseCollection

    shifts = [(sx, sy) for sx in (-L, 0, L) for sy in (-L, 0, L)]
    for sx, sy in shifts:
        offs = pos + np.array([sx, sy])
        keep = np.all((offs > -1) & (offs < L + 1), axis=1)
        coll = EllipseCollection(diam[keep], diam[keep], 0.0, units="xy", offsets=offs[keep],
                                 transOffset=ax.transData, facecolors=np.asarray(colors)[keep],
                                 edgecolors="0.4", linewidths=lw)
        ax.add_collection(coll)


def _bonds(ax, pos, c, **kw):
    """Contacts as segments, drawn from both ends so that bonds across the box edge show on
    both sides."""
    from matplotlib.collections import LineCollection

    seg = np.concatenate([np.stack([pos[c.i], pos[c.i] + c.rij], axis=1),
                          np.stack([pos[c.j] - c.rij, pos[c.j]], axis=1)])
    ax.add_collection(LineCollection(seg, **kw))


def _save(plt, fig, path, colors=64):
    """PNG at DPI, palette-quantised when Pillow is there (the docs keep small images)."""
    readable_log_ticks(fig)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    try:
        from PIL import Image
    except ImportError:
        return
    with Image.open(path) as im:
        small = im.convert("RGB").quantize(colors)
    small.save(path, optimize=True)


def _frame(ax, L, heading):
    ax.set_xlim(0, L)
    ax.set_ylim(0, L)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title(heading, fontsize=9)


def softfig(pack, path, ncut=20, comm=None):
    """Fig. "softfig": a soft mode of a 2D packing after ``ncut`` contacts along x = L/2 are cut."""
    comm = comm or env.petsc().COMM_SELF
    cs = segment_cut(sm.prepare(pack, [sm.Plane(0, 0.5)]), sm.Plane(0, 0.5), ncut)
    count, V = soft_space(comm, cs)
    mode, ext = most_extended(comm, cs, V)
    whole = cs.gathered()
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 7.5))
    colors = np.where(np.isin(np.arange(pack.n), whole.original), "0.93", "0.75")
    _disks(ax, pack.pos, pack.diam, pack.L, colors, lw=0.2)
    u = mode.reshape(cs.n, cs.d)
    size = np.linalg.norm(u, axis=1)
    scale = 1.0 / np.percentile(size, 95)  # the 5% largest displacements exceed one diameter
    ax.quiver(cs.pos[:, 0], cs.pos[:, 1], u[:, 0] * scale, u[:, 1] * scale, angles="xy",
              scale_units="xy", scale=1.0, width=0.0018, headwidth=4, color="navy", zorder=2)
    _bonds(ax, whole.pos, whole.cut, colors="red", linewidths=3.0, zorder=3)
    _frame(ax, pack.L, f"{_state(pack)}: {ncut} contacts cut (red) along x = L/2; "
           f"{count - cs.d} soft modes besides the {cs.d} translations;\n"
           f"the most extended one (e = {ext:.2f}) as arrows")
    _save(plt, fig, path)
    return {"count": count, "q": ncut, "extension": ext}


def _state(pack):
    """N, d and the state of a packing (its label when its file gave one, else phi)."""
    label = pack.meta.get("state")
    label = label.decode() if isinstance(label, bytes) else label
    return title(pack.n, pack.d, label or f"phi = {pack.phi:.4f}")


def figs(pack, path, x0=0.5, m=2):
    """Fig. "figs": which contacts a cut removes (left: the plane x = x0 L, zoomed; right: the
    m^d sub-boxes of Section III) and which particles are left with fewer than d contacts."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 5.6))
    for ax, planes, zoom in ((axes[0], [sm.Plane(0, x0)], True),
                             (axes[1], sm.subdivision_planes(m, pack.d), False)):
        cs = sm.prepare(pack, planes)
        whole = cs.gathered()
        colors = np.full(pack.n, "0.75", dtype=object)
        colors[whole.original] = "0.95"
        colors[whole.original[whole.localised_particles]] = "orange"
        _disks(ax, pack.pos, pack.diam, pack.L, colors.astype(str))
        _bonds(ax, whole.pos, whole.kept, colors="0.25", linewidths=0.6)
        _bonds(ax, whole.pos, whole.cut, colors="red", linewidths=2.0)
        for p in planes:
            line = ax.axvline if p.axis == 0 else ax.axhline
            line(p.frac * pack.L, color="C0", ls="--", lw=1.0)
        heading = (f"plane x = {x0:g} L (zoom): q = {cs.q} contacts cut (red);\n"
                 f"orange: left with < d contacts ({cs.localised} localised modes)"
                 if zoom else f"{m}$^{pack.d}$ sub-boxes: q = {cs.q} contacts cut;\n"
                 "bonds wrapping across the box edge count at the planes at 0")
        _frame(ax, pack.L, heading)
        if zoom:
            w = 0.2 * pack.L
            ax.set_xlim(x0 * pack.L - w, x0 * pack.L + w)
            ax.set_ylim(0.5 * pack.L - w, 0.5 * pack.L + w)
    fig.suptitle(_state(pack), fontsize=10)
    _save(plt, fig, path)


def overlap_figure(path_h5, path):
    """From the file of ``parjam softmodes``: the overlap function f(x) (with and without the
    trivially localised modes, its lower bound c) and the extension e of every soft mode, sorted,
    against the threshold e0 of the extended subspace."""
    with h5py.File(path_h5, "r") as f:
        g = f["softmodes"]
        ov, ext = g["overlap"][()], np.sort(g["extension"][()])[::-1]
        c, cn, axis = (g["overlap"].attrs[k] for k in ("c", "c_nontrivial", "axis"))
        q, e0 = int(g["count"].attrs["q"]), float(g["trial_energy"].attrs["e0"])
        planes = " ".join(p.decode() if isinstance(p, bytes) else str(p)
                          for p in g.attrs["planes"])
    plt = pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(9.5, 3.6))
    ax[0].plot(ov[:, 0], ov[:, 1], "-o", ms=3, label="f(x)")
    ax[0].plot(ov[:, 0], ov[:, 2], "--s", ms=3, label="f(x), localised modes projected out")
    ax[0].axhline(c, color="k", ls=":", lw=0.8,
                  label=f"c = min f(x) = {c:.3f}; {cn:.3f} with the localised modes out")
    ax[0].set(xlabel=f"{axis} / L from the first plane", ylabel="f(x) L (integral 1)",
              title=f"overlap function, cut {planes} (q = {q} contacts)")
    ax[0].legend(fontsize=LEGEND_FONTSIZE)
    ax[1].semilogy(np.arange(1, len(ext) + 1), np.maximum(ext, 1e-16), ".", ms=3)
    ax[1].axhline(e0, color="k", ls="--", lw=0.8,
                  label=f"e0 = {e0:g}: q' = {int(np.sum(ext > e0))} of {len(ext)}")
    ax[1].set(xlabel="soft mode (by extension)", ylabel="extension e", title="extension")
    ax[1].legend(fontsize=LEGEND_FONTSIZE)
    about = describe(path_h5)
    fig.suptitle(title(about.get("n"), about.get("d"), about.get("state"),
                       what="soft modes of a cut packing"), fontsize=10)
    _save(plt, fig, path)


def log_ticks_at(axis, values, fmt="{:g}"):
    """A log axis labelled at the data's values only (no overlapping minor labels)."""
    from matplotlib.ticker import NullFormatter

    axis.set_ticks(values)
    axis.set_ticklabels([fmt.format(v) for v in values])
    axis.set_minor_formatter(NullFormatter())


def fx_vs_n_figure(results, path):
    """From the JSON of scripts/fx_vs_n.py (read, never recomputed): f(x) against x/L per N for
    the one-plane cut and the cube with all faces cut (bands: bootstrap errors over members),
    c and q'/q against N with the paper's variational bound, and the trial energies against L
    with their fitted exponents (docs/results/reproduction.md section 12)."""
    summary = results["summary"]
    geos = [g for g in ("plane", "faces") if summary.get(g, {}).get("per_N")]
    title = {"plane": "one plane cut (x = L/2)", "faces": "all faces cut (cube)"}
    plt = pyplot()
    fig, ax = plt.subplots(2, 3, figsize=(13, 7.6))
    cmap = plt.get_cmap("viridis")
    for k, geo in enumerate(geos):
        per = summary[geo]["per_N"]
        ns = sorted(per, key=int)
        a = ax[0, k]
        for j, n in enumerate(ns):
            s = per[n]
            x, f, err = (np.asarray(s[key], float) for key in ("x", "f", "f_err"))
            col = cmap(j / max(len(ns) - 1, 1))
            a.plot(x, f, "-o", ms=3, color=col, label=f"N = {n} ({s['members']} members), "
                   f"c = min f = {s['c']:.2f}")
            a.fill_between(x, f - np.nan_to_num(err), f + np.nan_to_num(err), color=col,
                           alpha=0.25, lw=0)
        a.axhline(1.0, color="0.5", lw=0.6, ls=":")
        a.set(xlabel="x / L from the cut", ylabel="f(x) L (integral 1)", title=title[geo])
        a.set_ylim(bottom=0)
        a.legend(fontsize=LEGEND_FONTSIZE)
    marks = {"plane": "o", "faces": "s"}
    a = ax[0, 2]
    for geo in geos:
        per = summary[geo]["per_N"]
        ns = sorted(per, key=int)
        N = np.array([int(n) for n in ns], float)
        for key, ls, lab in (("c", "-", "c"), ("c_nontrivial", "--", "c, localised out")):
            y = np.array([per[n][key] for n in ns])
            e = np.nan_to_num(np.array([per[n][key + "_err"] for n in ns], float))
            a.errorbar(N, y, e, marker=marks[geo], ls=ls, ms=4, capsize=2,
                       label=f"{title[geo].split(' (')[0]}: {lab}")
    a.set_xscale("log")
    log_ticks_at(a.xaxis, N)
    a.set(xlabel="N", ylabel="c = min f(x) L", title="lower bound c of f against N")
    a.set_ylim(0, 1)
    a.legend(fontsize=LEGEND_FONTSIZE)
    for k, geo in enumerate(geos):
        a = ax[1, k]
        per = summary[geo]["per_N"]
        ns = sorted(per, key=int)
        N = np.array([int(n) for n in ns], float)
        for i, e0 in enumerate(("0.05", "0.1", "0.2")):
            y = np.array([per[n][f"qpq_{e0}"] for n in ns])
            e = np.nan_to_num(np.array([per[n][f"qpq_{e0}_err"] for n in ns], float))
            line = a.errorbar(N, y, e, marker="o", ms=4, capsize=2, label=f"q'/q, e0 = {e0}")
            b = np.array([per[n][f"bound_mean_e_{e0}"] for n in ns])
            a.plot(N, np.maximum(b, 0), ls=":", color=line[0].get_color(),
                   label="bound (mean e - e0)/(1 - e0)" if i == 0 else None)
            if geo == "plane":
                bc = np.array([per[n][f"bound_c_{e0}"] for n in ns])
                a.plot(N, np.maximum(bc, 0), ls="--", color=line[0].get_color(), lw=0.8,
                       label="bound (c/2 - e0)/(1 - e0)" if i == 0 else None)
        a.set_xscale("log")
        log_ticks_at(a.xaxis, N)
        a.set(xlabel="N", ylabel="q'/q", title=f"extended fraction, {title[geo]}")
        a.set_ylim(0, 1.3 if geo == "plane" else 0.6)
        a.legend(fontsize=LEGEND_FONTSIZE, ncol=2, loc="upper center")
    a = ax[1, 2]
    for geo in geos:
        per, fit = summary[geo]["per_N"], summary[geo].get("fit_against_L", {})
        ns = sorted(per, key=int)
        L = np.array([per[n]["L"] for n in ns])
        for key, lab in (("omega_t2", "omega_t^2"), ("mean_modulated_energy", "<g dR|M|g dR>")):
            y = np.array([per[n][key] for n in ns])
            e = np.nan_to_num(np.array([per[n][key + "_err"] for n in ns], float))
            ex = fit.get(key)
            tag = f", L^({ex['exponent']:.2f} +- {ex['exponent_err']:.2f})" if ex else ""
            a.errorbar(L, y, e, marker=marks[geo], ms=4, capsize=2,
                       label=f"{geo}: {lab}{tag}")
    if geos:  # a guide ~ L^-2 through the first omega_t^2 point
        per0 = summary[geos[0]]["per_N"]
        n0 = sorted(per0, key=int)
        Ls = np.array([per0[n]["L"] for n in n0])
        a.plot(Ls, per0[n0[0]]["omega_t2"] * (Ls / Ls[0]) ** -2, "k:", lw=0.8, label="~ L^-2")
    a.set_xscale("log")
    a.set_yscale("log")
    if geos:
        log_ticks_at(a.xaxis, Ls, "{:.1f}")
    a.set(xlabel="L (diameters)", ylabel="energy (k)", title="trial modes against L")
    lo, hi = a.get_ylim()
    a.set_ylim(lo, hi * 8)  # room for the legend above the curves
    a.legend(fontsize=LEGEND_FONTSIZE, loc="upper right")
    _save(plt, fig, path)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("packing", help="an isostatic 2D packing (about 1000 particles)")
    p.add_argument("--out-dir", default=".", help="where softfig.png and figs.png go")
    p.add_argument("--ncut", type=int, default=20, help="contacts cut for softfig (20)")
    args = p.parse_args(argv)
    env.init()
    pack = h5md.read_packing(args.packing)
    if pack.d != 2:
        raise sm.ParjamError("the figures need a 2D packing")
    os.makedirs(args.out_dir, exist_ok=True)
    info = softfig(pack, os.path.join(args.out_dir, "softfig.png"), args.ncut)
    figs(pack, os.path.join(args.out_dir, "figs.png"))
    print(f"softfig: {info}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
