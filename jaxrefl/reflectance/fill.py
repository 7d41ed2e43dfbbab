"""Filling parameters that could not be estimated, from mesh neighbours.

The paper interpolates inside a W x W window of the range image (W = 5). On a
mesh the window becomes the `(W - 1) / 2`-ring: the vertices at most that many
edges away. `window_fill` averages the measured values there; points with no
measured vertex in their window are then reached by repeated 1-ring averaging
(diffusion) and reported separately, so callers can flag them `unresolved`.

`precise_huber` (with `nearest_candidates`) is the robust alternative Method III
uses for its lobes: a Huber M-estimate over the nearest measured values, each
weighted by its precision, taken in order of distance until they pin the value
to a given precision.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
import trimesh
from scipy.spatial import cKDTree

__all__ = ["vertex_adjacency", "FillResult", "window_fill", "nearest_candidates", "precise_huber"]


def vertex_adjacency(faces, n_vertices: int) -> sp.csr_matrix:
    """Symmetric 0/1 vertex adjacency `(N, N)` of a triangle mesh (no self loops)."""
    edges = trimesh.geometry.faces_to_edges(np.asarray(faces, dtype=np.int64).reshape(-1, 3))
    a = trimesh.graph.edges_to_coo(edges, count=n_vertices).astype(np.float64).tocsr()
    a = ((a + a.T) > 0).astype(np.float64)
    a.setdiag(0)
    a.eliminate_zeros()
    return a


class FillResult(NamedTuple):
    """`values` `(N, C)` with every row set; `window` `(N,)` bool: filled from
    measured vertices inside the window; `diffused` `(N,)` bool: filled from
    farther away (or, in a component with nothing measured, the global median)."""

    values: np.ndarray
    window: np.ndarray
    diffused: np.ndarray


def window_reach(adjacency: sp.csr_matrix, window: int) -> sp.csr_matrix:
    """0/1 matrix `(N, N)`: entry `(u, v)` is 1 where `v` lies in the `(W - 1) / 2`-ring
    around `u` (`u` itself included)."""
    n = adjacency.shape[0]
    step = adjacency + sp.identity(n, format="csr")
    reach = sp.identity(n, format="csr")
    for _ in range((window - 1) // 2):
        reach = reach @ step
    return (reach > 0).astype(np.float64)


def window_fill(values, known, adjacency: sp.csr_matrix, window: int = 5, max_sweeps: int = 10_000) -> FillResult:
    """Fill rows of `values` `(N, C)` (or `(N,)`) where `known` `(N,)` is False.

    **Arguments:** `adjacency` from `vertex_adjacency`; `window` the paper's W
    (odd, >= 3): rows see the `(W - 1) / 2`-ring around them.
    """
    if window < 3 or window % 2 == 0:
        raise ValueError(f"window must be odd and >= 3, got {window}")
    vals = np.asarray(values, dtype=np.float64)
    squeeze = vals.ndim == 1
    vals = vals.reshape(len(vals), -1).copy()
    known = np.asarray(known, dtype=bool)
    if not known.any():
        raise ValueError("window_fill: no measured value to fill from")
    reach = window_reach(adjacency, window)
    k = known.astype(np.float64)
    counts = reach @ k
    sums = reach @ (vals * k[:, None])
    in_window = ~known & (counts > 0)
    out = vals.copy()
    out[in_window] = sums[in_window] / counts[in_window, None]

    filled = known | in_window
    far = ~filled
    # Diffuse outwards one ring per sweep: each unfilled row next to a filled one takes the mean
    # of its filled neighbours. Only the rows beside the last sweep's can grow, so each sweep
    # touches those rows alone (O(N) in all; a whole-matrix product per sweep is O(N^1.5)).
    new = np.flatnonzero(filled)
    sweeps = 0
    adjacency = adjacency.tocsr()
    while new.size and sweeps < max_sweeps:
        grow = np.unique(adjacency[new].indices)
        grow = grow[~filled[grow]]
        if not grow.size:
            break
        rows = adjacency[grow]  # every one has a filled neighbour: no empty row
        w = filled[rows.indices] * rows.data
        starts = rows.indptr[:-1]
        c = np.add.reduceat(w, starts)
        s = np.add.reduceat(out[rows.indices] * w[:, None], starts, axis=0)
        out[grow] = s / c[:, None]
        filled[grow] = True
        new = grow
        sweeps += 1
    orphan = ~filled  # components with nothing measured
    if orphan.any():
        out[orphan] = np.median(vals[known], axis=0)
    result = out[:, 0] if squeeze else out
    return FillResult(result, in_window, far)


def neighbour_tree(points) -> cKDTree:
    """A kd-tree over `points` `(n, 3)` for the nearest-neighbour searches of the fills and the
    prior. Sliding-midpoint splits, leaves of 64 points, cells not shrunk to their points:
    where a query lies far from every point (across a fold from a lit face, in a material's
    unmeasured part) its k-th neighbour sphere is wide, and with scipy's defaults it grazes
    many small cells (measurements: `benchmarks/RESULTS_notes.md`). The neighbours and their
    distances are the same; points at equal distance may come in another order."""
    return cKDTree(np.asarray(points, dtype=np.float64), leafsize=64, balanced_tree=False, compact_nodes=False)


def nearest_candidates(points, candidates, k: int) -> np.ndarray:
    """`(N, k')` int64: for every row of `points` `(N, 3)` the indices (into `points`)
    of its `k' = min(k, len(candidates))` nearest `candidates` (indices, Euclidean
    distance), nearest first."""
    cand = np.asarray(candidates, dtype=np.int64)
    if cand.size == 0:
        raise ValueError("nearest_candidates: no candidate")
    pts = np.asarray(points, dtype=np.float64)
    kk = int(min(k, cand.size))
    _, j = neighbour_tree(pts[cand]).query(pts, k=kk, workers=-1)
    return cand[np.asarray(j).reshape(len(pts), kk)]


def precise_huber(x, weight, nbr, target: float, steps: int = 30, start=None, affinity=None):
    """Robust pooled value of `x` `(N,)` over each row's candidates `nbr` `(N, K)` (nearest
    first), taking them in order until their weights (precisions, `1 / var` of `x`; 0
    where not measured; times `affinity` `(N, K)` in `[0, 1]` where given: how far
    candidate `k` speaks for row `n`) sum to `target` (all `K` where they never do): the Huber
    M-estimate `m` with `psi(m) = sum_j w_j clip(x_j - m, -c, c) = 0`, `c = 1 / sqrt(target)`.

    Without `start`: `steps` bisections of `psi` (monotone, piecewise linear) between the
    smallest and largest candidate taken, then one secant step: exact to the float
    precision by about 30 steps, whatever the spread. With `start` `(N,)` (a warm
    start, inside an iteration whose last value is near): `steps` iteratively
    re-weighted means, each lowering the Huber cost; cheap near the root, but slow
    (as a median's Weiszfeld steps) where the candidates lie farther apart than `c`.
    Pure `jnp`, no sort.

    **Returns:** `(value, total)` `(N,)`: the estimate (0 where `total` is 0) and the
    weight it rests on. A few imprecise neighbours are outvoted by farther precise
    ones, and a minority of wrong values counts only with weight `c / |x_j - m|`.
    """
    v, w = x[nbr], weight[nbr]
    if affinity is not None:
        w = w * affinity
    before = jnp.cumsum(w, axis=1) - w
    w = jnp.where(before < target, w, 0.0)
    total = jnp.sum(w, axis=1)
    c = 1.0 / jnp.sqrt(target)

    def psi(m):
        return jnp.sum(w * jnp.clip(v - m[:, None], -c, c), axis=1)

    if start is None:
        used = w > 0
        lo = jnp.min(jnp.where(used, v, jnp.inf), axis=1)
        hi = jnp.max(jnp.where(used, v, -jnp.inf), axis=1)
        lo, hi = jnp.where(total > 0, lo, 0.0), jnp.where(total > 0, hi, 0.0)

        def halve(bracket, _):
            lo, hi = bracket
            mid = 0.5 * (lo + hi)
            right = psi(mid) > 0  # the root lies above mid
            return (jnp.where(right, mid, lo), jnp.where(right, hi, mid)), None

        (lo, hi), _ = jax.lax.scan(halve, (lo, hi), None, length=steps)
        p_lo, p_hi = psi(lo), psi(hi)
        gap = p_lo - p_hi
        m = jnp.where(gap > 0, lo + p_lo * (hi - lo) / jnp.where(gap > 0, gap, 1.0), 0.5 * (lo + hi))
    else:
        def step(m, _):
            u = w * jnp.minimum(1.0, c / jnp.maximum(jnp.abs(v - m[:, None]), 1e-30))
            den = jnp.sum(u, axis=1)
            return jnp.where(den > 0, jnp.sum(u * v, axis=1) / jnp.where(den > 0, den, 1.0), m), None

        m, _ = jax.lax.scan(step, jnp.asarray(start).astype(jnp.result_type(v, w)), None, length=steps)
    return jnp.where(total > 0, m, 0.0), total
