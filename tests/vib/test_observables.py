"""Per-mode sums of parjam.vib.observables against the quadratic forms they stand for."""

import numpy as np
import pytest

from parjam.vib import hessian, observables


@pytest.mark.parametrize("d", [2, 3])
def test_trans_sums_are_the_unit_block_quadratic_forms_in_any_block_of_modes(d, monkeypatch):
    """Fig. "trans": eps_par = 1/2 v^T H_par v and eps_perp = 1/2 v^T H_perp v with H assembled
    from the blocks n n^T and I - n n^T of every contact; the same to round-off whether the modes
    go all at once or a few at a time (the block bounds the memory, never the result)."""
    rng = np.random.default_rng(7)
    n, nc, k = 12, 30, 9
    i = rng.integers(0, n, nc)
    j = (i + rng.integers(1, n, nc)) % n
    rij = rng.normal(size=(nc, d))
    r = np.linalg.norm(rij, axis=1)
    v = rng.normal(size=(k, n, d))
    flat = v.reshape(k, n * d)
    expect = {}
    for part in ("perp", "par"):
        H = hessian.dense_hessian(n, d, i, j, observables.unit_blocks(rij, r, part))
        expect[part] = 0.5 * np.einsum("ka,ab,kb->k", flat, H, flat)
    perp, par = observables.transverse_longitudinal(v, i, j, rij, r)
    np.testing.assert_allclose(perp, expect["perp"], rtol=1e-12)
    np.testing.assert_allclose(par, expect["par"], rtol=1e-12)
    monkeypatch.setattr(observables, "TRANS_BLOCK_VALUES", 2 * nc * d)  # 2 modes per block
    perp2, par2 = observables.transverse_longitudinal(v, i, j, rij, r)
    np.testing.assert_allclose(perp2, perp, rtol=1e-14)
    np.testing.assert_allclose(par2, par, rtol=1e-14)
