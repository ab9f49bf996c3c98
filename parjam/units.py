"""The reduced units of every number parjam prints or draws: lengths in sigma (the smallest
diameter of mono- and bidisperse packings), energies in epsilon (the prefactor of V(r)), times
in tau = sigma sqrt(m / epsilon) with unit masses.  ``text`` gives a CLI table's bracket,
``tex`` a figure axis's (matplotlib mathtext); d is the dimension where the unit depends on it
(pressure, moduli: energy per volume).  The files' ``unit`` attributes use the H5MD notation
(parjam.files.h5md)."""

#: quantity -> (plain text, mathtext); "{d}" stands for the dimension
UNITS = {
    "length": ("sigma", r"\sigma"),
    "energy": ("eps", r"\epsilon"),
    "time": ("tau", r"\tau"),
    "force": ("eps/sigma", r"\epsilon/\sigma"),
    "pressure": ("eps sigma^-{d}", r"\epsilon\,\sigma^{-{d}}"),
    "modulus": ("eps sigma^-{d}", r"\epsilon\,\sigma^{-{d}}"),
    "frequency": ("tau^-1", r"\tau^{-1}"),
    "eigenvalue": ("tau^-2", r"\tau^{-2}"),
    "dos": ("tau", r"\tau"),  # D(omega): modes per unit omega
    "speed": ("sigma/tau", r"\sigma/\tau"),
    "density": ("sigma^-{d}", r"\sigma^{-{d}}"),
    "wavenumber": ("sigma^-1", r"\sigma^{-1}"),
    "stiffness": ("eps sigma^-2", r"\epsilon\,\sigma^{-2}"),
}
GENERIC_D = "d"  # when the dimension is not known (a figure mixing 2D and 3D)


def text(quantity, d=GENERIC_D):
    """``[unit]`` for a CLI table or line, e.g. ``[eps sigma^-3]``."""
    return "[" + UNITS[quantity][0].replace("{d}", str(d)) + "]"


def tex(quantity, d=GENERIC_D):
    """``[$unit$]`` for a figure axis, e.g. ``[$\\tau^{-1}$]``."""
    return "[$" + UNITS[quantity][1].replace("{d}", str(d)) + "$]"


def axis(name, quantity, d=GENERIC_D):
    """An axis label: the quantity's name (mathtext allowed) and its unit."""
    return f"{name} {tex(quantity, d)}"
