"""Lobe fill: `fill.precise_huber` against the Huber estimating equation, and its rules."""

import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxrefl.methods.inverse_photon import _fill_lobes, _material_affinity
from jaxrefl.reflectance.fill import nearest_candidates, precise_huber


def _included(w, nbr, target, affinity):
    """Direct per-row loop: the candidates' weights (times their affinity), taken in order
    until they reach `target`."""
    out = np.zeros(nbr.shape)
    for i, row in enumerate(nbr):
        acc = 0.0
        for j, c in enumerate(row):
            if acc >= target:
                break
            out[i, j] = w[c] * affinity[i, j]
            acc += out[i, j]
    return out


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.sampled_from([1, 7, 30]), k=st.sampled_from([1, 4, 12]),
       target=st.floats(0.5, 50.0), zero_share=st.floats(0.0, 0.9), with_affinity=st.booleans())
def test_precise_huber_solves_the_huber_equation(seed, n, k, target, zero_share, with_affinity):
    """The value (default bisection steps) solves `sum_j w_j a_j clip(x_j - m, -c, c) = 0`
    over the candidates taken until the target (checked against a direct loop; `a` the
    affinity, 1 where none is given), `c = 1 / sqrt(target)`, and lies between their
    smallest and largest value; warm-started re-weighted means from it stay there."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=n) * rng.choice([0.01, 1.0], size=n)  # tight clusters and outliers
    w = np.where(rng.random(n) < zero_share, 0.0, rng.uniform(0.1, 10.0, n))
    nbr = nearest_candidates(rng.normal(size=(n, 3)), np.arange(n), k)
    aff = rng.choice([1e-6, 0.3, 1.0], size=nbr.shape) if with_affinity else np.ones(nbr.shape)
    got, tot = (np.asarray(a, np.float64) for a in precise_huber(
        jnp.asarray(x), jnp.asarray(w), jnp.asarray(nbr), target,
        affinity=jnp.asarray(aff) if with_affinity else None))
    wi = _included(w, nbr, target, aff)
    np.testing.assert_allclose(tot, wi.sum(1), rtol=1e-6)
    c = 1.0 / np.sqrt(target)
    v = x[nbr]
    for i in range(n):
        if tot[i] == 0:
            assert got[i] == 0.0
            continue
        used = wi[i] > 0
        assert v[i, used].min() - 1e-9 <= got[i] <= v[i, used].max() + 1e-9
        psi = np.sum(wi[i] * np.clip(v[i] - got[i], -c, c))
        assert abs(psi) <= 1e-4 * tot[i] * c, (psi, tot[i], c)
    warm, _ = precise_huber(jnp.asarray(x), jnp.asarray(w), jnp.asarray(nbr), target, steps=4,
                            start=jnp.asarray(got, jnp.float32), affinity=jnp.asarray(aff) if with_affinity else None)
    np.testing.assert_allclose(np.asarray(warm), got, atol=1e-5 * (1 + np.abs(x).max()))


def test_precise_lobe_stands_alone_loose_ones_are_outvoted():
    """Points on a line, candidates nearest first: a value known to the target precision
    is kept; a loose wrong value beside precise right ones is outvoted; a point with no
    measured candidate reports total 0."""
    pts = np.c_[[-10.0, 1.0, 2.0, 3.0, 4.0, 5.0], np.zeros(6), np.zeros(6)]
    x = np.array([1.0, 5.0, 2.0, 2.0, 2.0, 0.0])
    w = np.array([100.0, 1.0, 30.0, 30.0, 30.0, 0.0])
    nbr = nearest_candidates(pts, np.arange(6), 6)
    val, tot = (np.asarray(a) for a in precise_huber(jnp.asarray(x), jnp.asarray(w), jnp.asarray(nbr), 60.0))
    assert val[0] == 1.0 and tot[0] == 100.0  # alone: its own weight reaches the target
    # 5 (weight 1) with 2, 2 (30 each) up to the target: counted with weight c / 3 only
    assert abs(val[1] - 2.0) < 0.01 and tot[1] == 61.0
    assert val[5] == 2.0 and tot[5] == 60.0  # unmeasured itself: filled from the nearest measured
    _, tot0 = precise_huber(jnp.asarray(x), jnp.zeros(6), jnp.asarray(nbr), 60.0)
    assert np.all(np.asarray(tot0) == 0.0)


def test_nearest_candidates_order_and_bounds():
    pts = np.c_[np.arange(5.0), np.zeros(5), np.zeros(5)]
    nbr = nearest_candidates(pts, [4, 0, 2], 10)
    assert nbr.shape == (5, 3)
    np.testing.assert_array_equal(nbr[1], [0, 2, 4])  # distances 1, 1 (tie: either order), 3
    np.testing.assert_array_equal(nbr[4], [4, 2, 0])


def test_lobe_fill_pools_within_a_material():
    """Two materials side by side on a line, pd 0.1 (x < 0) and 0.6 (x >= 0), lobes ps 0.6
    and 0.05, each measured at a few points far from the edge: the unmeasured points next
    to the edge take their own material's lobe although the other one's are nearer, and
    with `fill_pd_scale` 0 (pd ignored) the nearest material's. A row of a third pd, with
    no alike candidate, takes the most alike material's lobe."""
    x = np.r_[np.linspace(-1.0, -0.1, 10), np.linspace(0.0, 0.9, 10), [5.0]]
    pts = np.c_[x, np.zeros_like(x), np.zeros_like(x)]
    pd = np.where(x[:, None] < 0, 0.1, 0.6) * np.ones((len(x), 3))
    pd[-1] = 0.5  # nearer 0.6 (relative distance 0.18) than 0.1 (1.33)
    ps = np.where(x < 0, 0.6, 0.05)
    known = np.zeros(len(x), bool)
    known[[0, 1, 2, 17, 18, 19]] = True  # measured far from the edge only
    nbr = jnp.asarray(nearest_candidates(pts, np.flatnonzero(known), 6))
    sd = jnp.full(len(x), 0.01)
    rho = jnp.zeros(len(x))
    args = (jnp.asarray(ps), rho, jnp.asarray(known), sd, sd, nbr, 1.0 / 0.02**2)
    for scale, edge_left, edge_right in ((0.2, 0.6, 0.05), (0.0, 0.6, 0.6)):
        got, _ = _fill_lobes(*args, affinity=_material_affinity(jnp.asarray(pd), nbr, scale))
        got = np.asarray(got)
        assert abs(got[9] - edge_left) < 1e-3 and abs(got[10] - edge_right) < 1e-3, (scale, got[8:12])
        if scale:
            assert abs(got[-1] - 0.05) < 1e-3  # the most alike material, though the other is as near
            np.testing.assert_allclose(got[known], ps[known], rtol=1e-6)
