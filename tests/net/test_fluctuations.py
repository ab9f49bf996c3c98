"""Contact-number fluctuations in sub-boxes (parjam.net.fluctuations) against an independent count
box by box, and the sums over sub-boxes against the whole network.  Serial and under mpirun
(no MPI inside: every rank checks the same packing)."""

import os

import numpy as np
import pytest

from parjam.files import h5md
from parjam.net import network
from parjam.net.fluctuations import contact_fluctuations
from conftest import DATA



@pytest.fixture(scope="module", params=["lengths_d2_N1024_dphi1e-01.h5",
                                        "ref_d3_mono_N128_dphi1e-03.h5"])
def packed(request):
    pack = h5md.read_packing(os.path.join(DATA, request.param))
    return pack, network.analyze(pack)


def brute_counts(pack, net, m):
    """Contacts (by midpoint) and non-rattlers per sub-box, one box at a time."""
    c = net.contacts
    mid = np.mod(pack.pos[c.i] + 0.5 * c.rij, pack.L)
    act = np.mod(pack.pos[~net.rattler], pack.L)
    side = pack.L / m
    nc, npart = [], []
    for corner in np.ndindex(*(m,) * pack.d):
        lo = np.array(corner) * side
        hi = lo + side
        inside = (lambda x: np.all((x >= lo) & ((x < hi) | (np.array(corner) == m - 1)), axis=1))
        nc.append(inside(mid).sum())
        npart.append(inside(act).sum())
    return np.array(nc, float), np.array(npart, float)


def test_sub_box_counts_equal_a_brute_force_count(packed):
    pack, net = packed
    res = contact_fluctuations(pack, 6)
    ms = np.rint(pack.L / res["l"]).astype(int)
    assert ms[0] == 1 and list(ms) == list(range(1, len(ms) + 1))
    assert len(ms) >= 2  # at least one real subdivision
    assert np.all(res["l"][1:] >= 2.0 * pack.diam.max())  # boxes stay above two diameters
    for k, m in enumerate(ms):
        nc, npart = brute_counts(pack, net, m)
        # every contact and non-rattler lies in exactly one sub-box
        assert nc.sum() == net.n_contacts and npart.sum() == net.n_active
        assert res["mean_contacts"][k] == pytest.approx(nc.mean(), rel=1e-12)
        assert res["mean_particles"][k] == pytest.approx(npart.mean(), rel=1e-12)
        assert res["var_contacts"][k] == pytest.approx(nc.var(), rel=1e-9, abs=1e-12)
        excess = nc - 0.5 * net.z * npart
        assert res["var_excess"][k] == pytest.approx(excess.var(), rel=1e-9, abs=1e-12)
    # the whole box: no fluctuation, and its excess over (z/2) N' is zero by definition of z
    assert res["var_contacts"][0] == 0.0 and res["var_excess"][0] == pytest.approx(0.0, abs=1e-9)
    assert res["dz"] == pytest.approx(net.dz) and res["L"] == pack.L
