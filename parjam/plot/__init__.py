"""Figures (PNG, matplotlib with the Agg backend), one submodule per topic; ``parjam plot``
(parjam.commands.plot) draws them from result files."""

import contextlib
import os


DPI = 150  # every PNG: labels and legends (>= 8 pt) readable at the size they are drawn
LEGEND_FONTSIZE = 8


def pyplot():
    """matplotlib.pyplot on the non-interactive Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.rcParams.update({"savefig.dpi": DPI, "legend.fontsize": LEGEND_FONTSIZE})
    return plt


@contextlib.contextmanager
def atomic_png(path):
    """A temporary name (``.NAME.tmpPID.png`` in the same directory) to draw a PNG to, renamed
    to ``path`` when the block succeeds and removed when it fails: no partial image is ever
    left at ``path``.  Figures left open by a failed drawing are closed."""
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    tmp = os.path.join(directory, f".{os.path.basename(path)}.tmp{os.getpid()}.png")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        pyplot().close("all")
        raise
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
