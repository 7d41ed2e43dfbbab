"""Lobe fill: `fill.precise_median` against a direct weighted median, and its rules."""

import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxrefl.fill import nearest_candidates, precise_median


def _reference(x, w, nbr, target):
    """Direct per-row loop: candidates in order until the weights reach `target`, then
    the smallest value whose cumulative weight (sorted by value) reaches half."""
    out, tot = [], []
    for row in nbr:
        vals, ws, acc = [], [], 0.0
        for j in row:
            if acc >= target:
                break
            if w[j] > 0:
                vals.append(x[j])
                ws.append(w[j])
            acc += w[j]
        if not ws:
            out.append(0.0)
            tot.append(0.0)
            continue
        order = np.argsort(vals, kind="stable")
        v, c = np.asarray(vals)[order], np.cumsum(np.asarray(ws)[order])
        out.append(v[np.argmax(c >= 0.5 * c[-1])])
        tot.append(c[-1])
    return np.asarray(out), np.asarray(tot)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.sampled_from([1, 7, 30]), k=st.sampled_from([1, 4, 12]),
       target=st.floats(0.5, 50.0), zero_share=st.floats(0.0, 0.9))
def test_precise_median_matches_direct_weighted_median(seed, n, k, target, zero_share):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=n)
    w = np.where(rng.random(n) < zero_share, 0.0, rng.uniform(0.1, 10.0, n))
    pts = rng.normal(size=(n, 3))
    nbr = nearest_candidates(pts, np.arange(n), k)
    got, tot = precise_median(jnp.asarray(x), jnp.asarray(w), jnp.asarray(nbr), target)
    want, want_tot = _reference(x, w, nbr, target)
    np.testing.assert_allclose(np.asarray(tot), want_tot, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-6, atol=1e-12)


def test_precise_lobe_stands_alone_loose_ones_are_outvoted():
    """Points on a line, candidates nearest first: a value known to the target precision
    is kept; a loose wrong value beside precise right ones is outvoted; a point with no
    measured candidate reports total 0."""
    pts = np.c_[[-10.0, 1.0, 2.0, 3.0, 4.0, 5.0], np.zeros(6), np.zeros(6)]
    x = np.array([1.0, 5.0, 2.0, 2.0, 2.0, 0.0])
    w = np.array([100.0, 1.0, 30.0, 30.0, 30.0, 0.0])
    nbr = nearest_candidates(pts, np.arange(6), 6)
    val, tot = (np.asarray(a) for a in precise_median(jnp.asarray(x), jnp.asarray(w), jnp.asarray(nbr), 60.0))
    assert val[0] == 1.0 and tot[0] == 100.0  # alone: its own weight reaches the target
    assert val[1] == 2.0 and tot[1] == 61.0  # 5 (weight 1) with 2, 2 (30 each) up to the target
    assert val[5] == 2.0 and tot[5] == 60.0  # unmeasured itself: filled from the nearest measured
    _, tot0 = precise_median(jnp.asarray(x), jnp.zeros(6), jnp.asarray(nbr), 60.0)
    assert np.all(np.asarray(tot0) == 0.0)


def test_nearest_candidates_order_and_bounds():
    pts = np.c_[np.arange(5.0), np.zeros(5), np.zeros(5)]
    nbr = nearest_candidates(pts, [4, 0, 2], 10)
    assert nbr.shape == (5, 3)
    np.testing.assert_array_equal(nbr[1], [0, 2, 4])  # distances 1, 1 (tie: either order), 3
    np.testing.assert_array_equal(nbr[4], [4, 2, 0])
