"""Figures (PNG, matplotlib with the Agg backend), one submodule per topic; ``parjam plot``
(parjam.commands.plot) draws them from result files."""

import contextlib

from parjam.files import outputs


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
    left at ``path`` (parjam.files.outputs: the output policy; a full disk is one line).  Figures
    left open by a failed drawing are closed."""
    try:
        with outputs.atomic_path(path, ".png", make_dirs=True) as tmp:
            yield tmp
    except BaseException:
        pyplot().close("all")
        raise
