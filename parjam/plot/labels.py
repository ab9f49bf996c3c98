"""What every figure says about itself: a title naming the state (N, d, dphi or p, members),
axes with reduced units (parjam.units), and log axes with enough labelled ticks to be read."""

import json
import math
import os
import re

import numpy as np

from parjam import units


def state_text(label):
    """A state label of parjam's files in words: ``dphi1.0e-04`` -> ``dphi = 1e-04``,
    ``p1.0e-03`` -> ``p = 1e-03``, ``phi_c``; others as they are."""
    label = str(label or "")
    m = re.fullmatch(r"(dphi|p)([0-9.]+e[+-]?[0-9]+)", label)
    if m:
        name = r"$\delta\phi$" if m.group(1) == "dphi" else "p"
        return f"{name} = {float(m.group(2)):.0e}"
    return r"$\phi_c$" if label == "phi_c" else label


def title(n=None, d=None, state=None, members=None, what=None):
    """``what: N = 256, 3D, dphi = 1e-04, 8 members`` (the parts that are known)."""
    parts = []
    if n:
        parts.append(f"N = {int(n)}")
    if d:
        parts.append(f"{int(d)}D")
    if state:
        parts.append(", ".join(state_text(s) for s in str(state).split(",")))
    if members:
        parts.append(f"{int(members)} member{'s' if int(members) != 1 else ''}")
    text = ", ".join(parts)
    return f"{what}: {text}" if what and text else (what or text)


def _attr(obj, key):
    val = obj.attrs.get(key)
    if isinstance(val, bytes):
        val = val.decode()
    return val


def describe(path):
    """{n, d, state, members, pressure} of a result file for its title: from its own
    attributes (spectrum, D(omega), lengths files) and, where they are silent, from the
    /parameters of the packing its provenance names (softmodes, moduli, lengths files)."""
    import h5py

    out = {}
    with h5py.File(path, "r") as f:
        for group, keys in (("modes", {"state": "state", "n": "n", "d": "dimension",
                                       "pressure": "pressure"}),
                            ("dos", {"state": "state", "n": "n", "d": "dimension",
                                     "members": "n_files"}),
                            ("lengths", {"n": "N", "d": "d"}),
                            ("moduli", {"pressure": "pressure"})):
            if group in f:
                for key, attr in keys.items():
                    val = _attr(f[group], attr)
                    if val not in (None, "", 0) and key not in out:
                        out[key] = val
        prov = f["h5md/modules/parjam"].attrs if "h5md/modules/parjam" in f else {}
        source = prov.get("input")
        source = source.decode() if isinstance(source, bytes) else source
    if source and os.path.isfile(source) and not all(k in out for k in ("n", "d", "state")):
        try:
            with h5py.File(source, "r") as g:
                par = g["parameters"].attrs
                out.setdefault("state", _decoded(par.get("state")))
                out.setdefault("d", int(np.asarray(par.get("dimension", 0)).reshape(-1)[0]) or
                               g["particles/all/position/value"].shape[-1])
                out.setdefault("n", g["particles/all/diameter"].shape[0])
        except (OSError, KeyError, ValueError, TypeError):
            pass
    return out


def _decoded(val):
    return val.decode() if isinstance(val, bytes) else (str(val) if val is not None else None)


def members_of(prov_files):
    """The number of inputs a D(omega) file averaged (its provenance ``files``, JSON)."""
    try:
        return len(json.loads(prov_files))
    except (TypeError, ValueError):
        return None


def readable_log_ticks(fig):
    """Every log axis of ``fig`` with at least two labelled ticks: an axis spanning less than
    about two decades gets ticks at 1, 2, 5 (or finer) times powers of ten, labelled in plain
    numbers, and no minor labels (matplotlib labels a short log axis at one power of ten, or
    overprints long minor labels such as 2.9542x10^0)."""
    from matplotlib.ticker import FixedLocator, FuncFormatter, NullFormatter

    for ax in fig.axes:
        for axis, scale, limits in ((ax.xaxis, ax.get_xscale(), ax.get_xlim()),
                                    (ax.yaxis, ax.get_yscale(), ax.get_ylim())):
            if scale != "log" or isinstance(axis.get_major_locator(), FixedLocator):
                continue  # linear, or ticks the figure placed itself
            lo, hi = sorted(limits)
            if not (lo > 0 and np.isfinite(hi)) or hi / lo > 10**2.2:
                continue
            ticks = []
            for subs in ((1,), (1, 2, 5), (1, 1.5, 2, 3, 5, 7), tuple(np.arange(1, 10, 0.5))):
                ticks = [s * 10**e for e in range(math.floor(math.log10(lo)) - 1,
                                                  math.ceil(math.log10(hi)) + 1) for s in subs]
                ticks = [t for t in ticks if lo <= t <= hi]
                if len(ticks) >= 3:
                    break
            if len(ticks) < 2:  # less than a few per cent: the ends
                ticks = [lo, hi]
            axis.set_major_locator(FixedLocator(ticks))
            axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:.3g}"))
            axis.set_minor_formatter(NullFormatter())


def axis(name, quantity, d=units.GENERIC_D):
    """An axis label with its reduced unit (parjam.units.axis)."""
    return units.axis(name, quantity, d)
