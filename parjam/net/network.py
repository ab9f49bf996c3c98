"""The contact network of a packing: contacts, rattlers, coordination z, dz = z - 2d and
dz_iso = z - z_iso, the isostatic count, pressure, stress tensor and residual forces.

Conventions (the paper's, and the reference data's):
- a contact is an overlapping pair, r_ij < sigma_ij = (s_i + s_j)/2;
- rattlers have fewer than d + 1 contacts and are removed iteratively; N' particles remain,
  Nc contacts among them, z = 2 Nc / N', dz = z - z_c with z_c = 2d;
- isostatic count in a periodic box: Nc_iso = d (N' - 1) + 1, z_iso = 2 Nc_iso / N';
- two names, never mixed up: dz = z - 2d (slightly negative at phi_c, by -2(d - 1)/N') and
  dz_iso = z - z_iso = 2 (Nc - Nc_iso) / N' (zero at phi_c; the paper's delta z in the scaling
  laws and figures);
- pressure p = -(1/(d V)) sum_contacts r V'(r), stress sigma_ab = -(1/V) sum V'(r) r_a r_b / r.
"""

from dataclasses import dataclass

import numpy as np

from parjam.net import potential
from parjam.net.system import neighbour_pairs, pair_geometry


@dataclass
class Contacts:
    """Contacts with their geometry, rij = x_j - x_i.  Serially (``find_contacts``): all
    overlapping pairs i < j, rattlers included.  In parjam.net.active: a rank's half-edges, i owned,
    j owned or ghost, both given by their global active numbers."""

    i: np.ndarray
    j: np.ndarray
    rij: np.ndarray
    r: np.ndarray
    sigma: np.ndarray

    def __len__(self):
        return len(self.i)

    @property
    def unit(self):
        """Unit vectors n = r_ij / r."""
        return self.rij / self.r[:, None]

    def subset(self, mask):
        return Contacts(self.i[mask], self.j[mask], self.rij[mask], self.r[mask], self.sigma[mask])


def find_contacts(pack):
    pairs = neighbour_pairs(pack.pos, pack.L, pack.diam.max() * (1.0 + 1e-9))
    rij, r, sigma = pair_geometry(pack.pos, pack.L, pack.diam, pairs)
    c = r < sigma
    return Contacts(pairs[c, 0], pairs[c, 1], rij[c], r[c], sigma[c])


def find_rattlers(n, d, contacts):
    """Boolean mask of rattlers: fewer than d+1 contacts, removed iteratively."""
    rattler = np.zeros(n, dtype=bool)
    keep = np.ones(len(contacts), dtype=bool)
    while True:
        deg = np.bincount(contacts.i[keep], minlength=n) + np.bincount(contacts.j[keep], minlength=n)
        new = (deg < d + 1) & ~rattler
        if not new.any():
            return rattler
        rattler |= new
        keep &= ~(rattler[contacts.i] | rattler[contacts.j])


def contact_forces(pack, contacts):
    """Force vectors on j from i for every contact (on i it is the negative)."""
    dv = potential.dV(contacts.r, contacts.sigma, pack.alpha, pack.eps)
    return -(dv / contacts.r)[:, None] * contacts.rij


def particle_forces(pack, contacts):
    fj = contact_forces(pack, contacts)
    F = np.zeros_like(pack.pos)
    for a in range(pack.d):
        F[:, a] = (np.bincount(contacts.j, weights=fj[:, a], minlength=pack.n)
                   - np.bincount(contacts.i, weights=fj[:, a], minlength=pack.n))
    return F


def stress_tensor(pack, contacts):
    dv = potential.dV(contacts.r, contacts.sigma, pack.alpha, pack.eps)
    w = -(dv / contacts.r)[:, None, None]
    return (w * contacts.rij[:, :, None] * contacts.rij[:, None, :]).sum(axis=0) / pack.volume


class NetworkNumbers:
    """The numbers of a contact network from N, d, N', Nc and the summed observables: shared by
    the serial :class:`Network` and the distributed parjam.net.active.ActiveNetwork."""

    @property
    def n_iso(self):
        return self.d * (self.n_active - 1) + 1

    @property
    def excess(self):
        """Nc - Nc_iso."""
        return self.n_contacts - self.n_iso

    @property
    def z(self):
        return 2.0 * self.n_contacts / self.n_active if self.n_active else 0.0

    @property
    def dz(self):
        """z - 2d."""
        return self.z - 2.0 * self.d

    @property
    def dz_iso(self):
        """z - z_iso = 2 (Nc - Nc_iso) / N' (module doc)."""
        return 2.0 * self.excess / self.n_active if self.n_active else 0.0

    def summary(self):
        return {
            "phi": self.phi, "N": self.n, "N_active": self.n_active,
            "n_rattlers": self.n_rattlers, "Nc": self.n_contacts, "Nc_iso": self.n_iso,
            "excess": self.excess, "z": self.z, "dz": self.dz, "dz_iso": self.dz_iso,
            "pressure": self.pressure,
            "energy_per_particle": self.energy / self.n, "max_force": self.max_force,
            "max_force_rel": self.max_force / self.mean_force if self.mean_force else np.inf,
        }


@dataclass
class Network(NetworkNumbers):
    """Summary of a packing's contact network (all the numbers `parjam analyze` prints)."""

    n: int
    d: int
    phi: float
    contacts: Contacts  # among non-rattlers
    all_contacts: Contacts
    rattler: np.ndarray
    energy: float
    pressure: float
    stress: np.ndarray
    max_force: float
    mean_force: float
    # per contact of all_contacts (the file's /connectivity): overlap 1 - r / sigma_ij,
    # force |V'(r)| and stiffness V''(r)
    overlap: np.ndarray = None
    force: np.ndarray = None
    stiffness: np.ndarray = None

    @property
    def n_active(self):
        return int((~self.rattler).sum())

    @property
    def n_contacts(self):
        return len(self.contacts)

    @property
    def n_rattlers(self):
        return int(self.rattler.sum())


def active_index(rattler):
    """The serial re-index of the non-rattlers: 0..N'-1 in particle order, -1 for rattlers
    (the distributed one is parjam.net.active.renumber)."""
    keep = ~np.asarray(rattler, dtype=bool)
    index = np.cumsum(keep) - 1
    index[~keep] = -1
    return index


def active_contacts(net):
    """The contacts among non-rattlers with both ends in the serial re-index."""
    index = active_index(net.rattler)
    c = net.contacts
    return Contacts(index[c.i], index[c.j], c.rij, c.r, c.sigma)


def analyze(pack):
    """Contacts, rattlers, z, pressure, stress and residual forces of a packing."""
    allc = find_contacts(pack)
    rattler = find_rattlers(pack.n, pack.d, allc)
    active = allc.subset(~(rattler[allc.i] | rattler[allc.j]))
    F = particle_forces(pack, allc)
    fnorm = np.sqrt(np.einsum("ij,ij->i", F, F))
    max_force = float(fnorm[~rattler].max()) if (~rattler).any() else 0.0
    fmag = np.abs(potential.dV(active.r, active.sigma, pack.alpha, pack.eps))
    stress = stress_tensor(pack, allc)
    return Network(
        n=pack.n, d=pack.d, phi=pack.phi, contacts=active, all_contacts=allc, rattler=rattler,
        energy=float(potential.energy(allc.r, allc.sigma, pack.alpha, pack.eps).sum()),
        pressure=float(np.trace(stress) / pack.d), stress=stress, max_force=max_force,
        mean_force=float(fmag.mean()) if len(fmag) else 0.0,
        overlap=potential.overlap(allc.r, allc.sigma),
        force=np.linalg.norm(contact_forces(pack, allc), axis=1) if len(allc) else np.zeros(0),
        stiffness=potential.d2V(allc.r, allc.sigma, pack.alpha, pack.eps),
    )
