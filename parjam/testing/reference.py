"""Dense references for the tests: the whole non-rattler system of a packing built from the
serial contact network (parjam.net.network, a construction independent of the distributed one
the commands use), its dense matrices, and the distributed system of the same packing."""

from dataclasses import dataclass

import numpy as np

from parjam import env
from parjam.net import network
from parjam.net.system import Packing
from parjam.vib import spectrum
from parjam.vib.dense import DenseSystem, dense_matrix


def dense_system(pack, net=None):
    """The non-rattlers of ``pack`` from its serial network, rows in ascending particle id
    and every contact once (i < j); ParjamError/UnjammedError if it cannot vibrate."""
    net = net if net is not None else network.analyze(pack)
    spectrum.check_vibrates(pack.n, pack.d, len(net.all_contacts), net.n_active,
                            net.n_contacts, net.n_iso)
    c = network.active_contacts(net)
    return DenseSystem(n=net.n_active, d=pack.d, ids=np.flatnonzero(~net.rattler), i=c.i,
                       j=c.j, rij=c.rij, r=c.r, sigma=c.sigma, alpha=pack.alpha, eps=pack.eps)


@dataclass
class Case:
    """A packing with its distributed system on a communicator (what the commands compute on)
    and its dense reference (what the tests compare with)."""

    pack: Packing
    system: spectrum.ActiveSystem
    ref: DenseSystem

    @property
    def n(self):
        return self.ref.n

    @property
    def d(self):
        return self.ref.d

    @property
    def n_modes(self):
        return self.ref.n_modes

    def on(self, comm):
        """The distributed system of the same packing on another communicator."""
        return spectrum.system_of(comm, self.pack)

    def matrix(self, kind):
        """The dense matrix of one kind, rows in ascending particle id."""
        return dense_matrix(self.ref, kind)


def case(pack, comm=None, net=None):
    """The Case of ``pack`` on ``comm`` (default: PETSc's COMM_WORLD; collective)."""
    comm = comm if comm is not None else env.petsc().COMM_WORLD
    return Case(pack, spectrum.system_of(comm, pack), dense_system(pack, net))
