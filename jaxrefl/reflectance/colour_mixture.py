"""Colour clusters with one full covariance per cluster (`prior.fit_materials(...,
covariance="full")`).

An error that a surface's three channels share (light the forward model misses beside a concave
fold, shading) moves a grey point along the grey axis. A mixture with diagonal covariances follows
such a correlated cloud only with several components, and BIC then splits one material into
several; a full 3 x 3 covariance per component is the material. Each point's own variances are
deconvolved: the covariance takes the EM step of the model "true colour from the component, seen
through the point's own noise" (extreme deconvolution: Bovy, Hogg & Roweis 2011), which stays
positive definite and gives a loosely measured point little weight.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["em_batch", "assign"]

_VAR_FLOOR = 1e-8  # numerical floor of a covariance's eigenvalues (standardised units)
_EM_TOL = 1e-6  # relative gain of the log likelihood below which EM stops (as `prior`'s)
#: A symmetric 3 x 3 matrix is held as its six entries `(..., 6)` in this order (elementwise
#: arithmetic: batched LAPACK calls on millions of tiny matrices would dominate the mixture).
_PAIRS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
_EYE6 = np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0])


def _sym3_inverse(e):
    """Inverse `(..., 6)` and log determinant `(...)` of symmetric positive definite 3 x 3
    matrices `e` `(..., 6)` (`_PAIRS` order), by cofactors."""
    a00, a11, a22, a01, a02, a12 = (e[..., j] for j in range(6))
    c00, c11, c22 = a11 * a22 - a12 * a12, a00 * a22 - a02 * a02, a00 * a11 - a01 * a01
    c01, c02, c12 = a02 * a12 - a01 * a22, a01 * a12 - a02 * a11, a01 * a02 - a00 * a12
    det = jnp.maximum(a00 * c00 + a01 * c01 + a02 * c02, jnp.finfo(e.dtype).tiny)
    return jnp.stack([c00, c11, c22, c01, c02, c12], -1) / det[..., None], jnp.log(det)


def _sym3_matvec(e, d):
    """`e @ d` for symmetric `e` `(..., 6)` and vectors `d` `(..., 3)`."""
    return jnp.stack([e[..., 0] * d[..., 0] + e[..., 3] * d[..., 1] + e[..., 4] * d[..., 2],
                     e[..., 3] * d[..., 0] + e[..., 1] * d[..., 1] + e[..., 5] * d[..., 2],
                     e[..., 4] * d[..., 0] + e[..., 5] * d[..., 1] + e[..., 2] * d[..., 2]], -1)


def _sym3_smallest(e):
    """Smallest eigenvalue `(...)` of symmetric 3 x 3 matrices `e` `(..., 6)` (closed form:
    Smith 1961)."""
    q = (e[..., 0] + e[..., 1] + e[..., 2]) / 3.0
    off = e[..., 3] ** 2 + e[..., 4] ** 2 + e[..., 5] ** 2
    p = jnp.sqrt(((e[..., 0] - q) ** 2 + (e[..., 1] - q) ** 2 + (e[..., 2] - q) ** 2 + 2.0 * off) / 6.0)
    b = (e - q[..., None] * _EYE6.astype(e.dtype).reshape((1,) * q.ndim + (6,))) / jnp.where(p > 0, p, 1.0)[..., None]
    det = b[..., 0] * (b[..., 1] * b[..., 2] - b[..., 5] ** 2) - b[..., 3] * (b[..., 3] * b[..., 2] - b[..., 5] * b[..., 4]) \
        + b[..., 4] * (b[..., 3] * b[..., 5] - b[..., 1] * b[..., 4])
    phi = jnp.arccos(jnp.clip(det / 2.0, -1.0, 1.0)) / 3.0
    return jnp.where(p > 0, q + 2.0 * p * jnp.cos(phi + 2.0 * np.pi / 3.0), q)


def _sym3_full(e):
    """`(..., 3, 3)` matrices from their entries `e` `(..., 6)` (`_PAIRS`)."""
    return jnp.stack([e[..., [0, 3, 4]], e[..., [3, 1, 5]], e[..., [4, 5, 2]]], -2)


def _pair_mask(present):
    """`(n, 6)` bool: both channels of each entry (`_PAIRS`) present, from `present` `(n, 3)`."""
    return present[:, [i for i, _ in _PAIRS]] & present[:, [j for _, j in _PAIRS]]


def _log_density(x, v, mu, cov, log_w):
    """Per point and component `(log density (n, K), inverse covariances (n, K, 6))` of
    colours `x`, `v` `(n, 3)` (v inf: missing channel) under components `mu` `(K, 3)`, `cov`
    `(K, 6)`, weights `log_w` `(K,)`. Each point's covariance is the component's plus its own
    variances; a missing channel is decoupled (unit variance, no covariance, no deviation),
    so it drops out, and its entries of the inverse are 0 (no information)."""
    present = jnp.isfinite(v)
    pairs = _pair_mask(present)[:, None]  # (n, 1, 6)
    own = jnp.concatenate([jnp.where(present, v, 0.0), jnp.zeros_like(v)], -1)  # (n, 6)
    c = jnp.where(pairs, cov[None] + own[:, None], _EYE6.astype(cov.dtype)[None, None])
    inv, logdet = _sym3_inverse(c)
    dx = jnp.where(present[:, None], x[:, None] - mu[None], 0.0)  # (n, K, 3)
    quad = jnp.sum(dx * _sym3_matvec(inv, dx), -1)
    minus2 = quad + logdet + present.sum(1)[:, None] * float(np.log(2 * np.pi))
    return log_w[None] - 0.5 * minus2, jnp.where(pairs, inv, 0.0)


@partial(jax.jit, static_argnames=("iterations",))
def em_batch(x, v, weight, resp, active, iterations=100):
    """EM of colour mixtures with full covariances and per-point observation variances, one
    per batch row. `x`, `v` `(n, 3)` (v inf: missing channel); `weight` `(n,)` 1 for a point,
    0 for padding; `resp` `(B, n, K)` initial responsibilities; `active` `(B, K)` the
    components each row uses. Returns per row the log likelihood `(B,)`, `mu` `(B, K, 3)`,
    `cov` `(B, K, 6)`, `log_w` `(B, K)` and `collapsed` `(B,)` (a component fell under 6 points)."""
    n = weight.sum()
    present = jnp.isfinite(v) & (weight[:, None] > 0)
    xx = jnp.where(present, x, 0.0)
    pairs = _pair_mask(present)[:, None]  # (n, 1, 6): entries whose channels are both present
    v_in = jnp.where(present, v, jnp.inf)
    dtype = x.dtype
    eye6 = _EYE6.astype(dtype)
    tol = max(_EM_TOL, 10 * float(jnp.finfo(dtype).eps))

    def one(resp0, act):
        k = resp0.shape[1]

        def step(state):
            resp, mu, _, cov, inv, ll, _, it, collapsed = state
            resp = resp * weight[:, None]
            nk = resp.sum(0)
            collapsed = collapsed | jnp.any(act & (nk < 6.0))
            log_w = jnp.where(act, jnp.log(jnp.maximum(nk, 1e-30) / n), -jnp.inf)
            # The mean is the generalised least-squares one under each point's covariance
            # (component's plus its own: `inv`, from the last E-step); the covariance takes the
            # deconvolution EM step `cov + cov (G - L) cov / n_k`, `L` the summed inverses,
            # `G` the summed outer products of `inv (x - mu)`.
            rinv = resp[:, :, None] * inv  # (n, K, 6)
            lhs = rinv.sum(0) + jnp.where(jnp.any(pairs, 0), 0.0, eye6[None])
            rhs = jnp.sum(_sym3_matvec(rinv, xx[:, None]), 0)
            mu = _sym3_matvec(_sym3_inverse(lhs)[0], rhs)
            g = _sym3_matvec(inv, jnp.where(present[:, None], xx[:, None] - mu[None], 0.0))
            gg = jnp.sum(resp[:, :, None] * jnp.stack([g[..., i] * g[..., j] for i, j in _PAIRS], -1), 0)
            full = _sym3_full(cov)
            inner = jnp.matmul(full, _sym3_full(gg - rinv.sum(0)), precision=jax.lax.Precision.HIGHEST)
            delta = jnp.matmul(inner, full, precision=jax.lax.Precision.HIGHEST) / jnp.maximum(nk, 1e-30)[:, None, None]
            cov = cov + jnp.stack([delta[:, i, j] for i, j in _PAIRS], -1)
            cov = cov + jnp.maximum(_VAR_FLOOR - _sym3_smallest(cov), 0.0)[:, None] * eye6[None]
            logp, inv = _log_density(x, v_in, mu, cov, log_w)
            total = jax.nn.logsumexp(logp, axis=1)
            return (jnp.exp(logp - total[:, None]), mu, log_w, cov, inv, jnp.sum(total * weight), ll, it + 1,
                    collapsed)

        def going(state):
            ll, previous, it, collapsed = state[5:]
            return (it < iterations) & ~collapsed & ((it < 1) | (ll - previous >= tol * jnp.abs(ll) + 1e-9))

        mu0, cov0, log_w0 = jnp.zeros((k, 3), dtype), jnp.broadcast_to(eye6, (k, 6)), jnp.full(k, -jnp.log(k), dtype)
        init = (resp0, mu0, log_w0, cov0, _log_density(x, v_in, mu0, cov0, log_w0)[1],
                jnp.asarray(-jnp.inf, dtype), jnp.asarray(-jnp.inf, dtype), 0, jnp.asarray(False))
        _, mu, log_w, cov, _, ll, _, _, collapsed = jax.lax.while_loop(going, step, init)
        return ll, mu, cov, log_w, collapsed

    return jax.vmap(one)(resp, active)


@jax.jit
def _assign_block(x, v, mu, cov, log_w):
    return jnp.argmax(_log_density(x, v, mu, cov, log_w)[0], axis=1)


def assign(x, v, mu, cov, log_w, block: int = 8192) -> np.ndarray:
    """`(n,)` the most probable component of each colour `x`, `v` `(n, 3)`, in blocks of
    `block` points (one compilation for any n)."""
    n = len(x)
    pad = -n % block
    x = np.pad(x, [(0, pad), (0, 0)])
    v = np.pad(v, [(0, pad), (0, 0)], constant_values=np.inf)
    out = [np.asarray(_assign_block(x[i:i + block], v[i:i + block], mu, cov, log_w))
           for i in range(0, n + pad, block)]
    return np.concatenate(out)[:n].astype(np.int64)
