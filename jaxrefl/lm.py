"""Per-row nonlinear least squares: a fixed-step Levenberg-Marquardt in plain `jnp`.

Every row (surface point) has its own small problem: a residual vector
`r(p, data) -> (R,)` in a handful of parameters `p` `(P,)`. `solve_rows` runs
`steps` damped Gauss-Newton steps on all rows at once (`vmap` inside one
`jit`): no per-row while loop, so no row waits for the slowest one, and no
Python loop over points. A step is kept only if it lowers the cost; the
damping grows tenfold on a rejected step and shrinks threefold on an accepted
one (Marquardt's scaling by the diagonal of `J^T J`).

`covariance` turns the final Jacobian and residual into a Gauss-Newton
(Laplace) covariance `s^2 (J^T J)^-1` with `s^2 = cost / (R_valid - P)`.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp

__all__ = ["LMResult", "solve_rows", "covariance", "spd_solve"]


class LMResult(NamedTuple):
    """Per-row results: `params` `(N, P)`, `cost` `(N,)` (sum of squared
    residuals), `accepted` `(N,)` number of accepted steps, `finite` `(N,)`
    bool (cost and parameters finite)."""

    params: jax.Array
    cost: jax.Array
    accepted: jax.Array
    finite: jax.Array


def spd_solve(a, b):
    """Solve `a x = b` for one small symmetric positive definite `a` `(P, P)`.

    Cholesky written out over the (static) matrix size: under `vmap` every
    entry becomes one elementwise operation over all rows, far faster on a CPU
    than batched LAPACK calls on tiny matrices.
    """
    n = a.shape[0]
    low = [[None] * n for _ in range(n)]
    for i in range(n):
        for j in range(i + 1):
            acc = a[i, j] - sum((low[i][k] * low[j][k] for k in range(j)), 0.0)
            if i == j:
                low[i][i] = jnp.sqrt(jnp.maximum(acc, 1e-300))
            else:
                low[i][j] = acc / low[j][j]
    z = [None] * n
    for i in range(n):
        z[i] = (b[i] - sum((low[i][k] * z[k] for k in range(i)), 0.0)) / low[i][i]
    x = [None] * n
    for i in reversed(range(n)):
        x[i] = (z[i] - sum((low[k][i] * x[k] for k in range(i + 1, n)), 0.0)) / low[i][i]
    return jnp.stack(x)


def _cost(residual, p, data):
    r = residual(p, data)
    return jnp.sum(r * r)


def _solve_row(residual, p0, data, steps, damping):
    n_par = p0.shape[0]

    def body(_, state):
        p, lam, cost, accepted = state
        r = residual(p, data)
        jac = jax.jacfwd(residual)(p, data)
        jtj = jac.T @ jac
        g = jac.T @ r
        scale = jnp.diag(jtj) + 1e-12
        step = spd_solve(jtj + lam * jnp.diag(scale) + 1e-15 * jnp.eye(n_par), -g)
        step = jnp.where(jnp.all(jnp.isfinite(step)), step, 0.0)
        p_new = p + step
        cost_new = _cost(residual, p_new, data)
        ok = jnp.isfinite(cost_new) & (cost_new < cost)
        return (jnp.where(ok, p_new, p), jnp.where(ok, lam / 3.0, lam * 10.0),
                jnp.where(ok, cost_new, cost), accepted + ok)

    cost0 = _cost(residual, p0, data)
    p, _, cost, accepted = jax.lax.fori_loop(0, steps, body, (p0, damping, cost0, 0))
    finite = jnp.isfinite(cost) & jnp.all(jnp.isfinite(p))
    return LMResult(p, cost, accepted, finite)


@partial(jax.jit, static_argnums=(0, 3))
def solve_rows(residual, p0, data, steps: int = 20, damping: float = 1e-3) -> LMResult:
    """Minimise `sum(residual(p, data_row)**2)` for every row.

    **Arguments:** `residual` a pure function of one row's `(p (P,), data)`;
    `p0` `(N, P)` starting points (a good closed-form guess matters: the step
    count is fixed); `data` a pytree whose leaves have a leading `N` axis;
    `steps` number of LM steps; `damping` initial Marquardt parameter.

    **Returns:** `LMResult`.
    """
    return jax.vmap(lambda p, d: _solve_row(residual, p, d, steps, damping))(p0, data)


@partial(jax.jit, static_argnums=0)
def covariance(residual, params, data, n_valid):
    """Gauss-Newton covariance `(N, P, P)` of every row at `params` `(N, P)`.

    `n_valid` `(N,)` counts the residuals that carry data (masked entries are
    0 and add nothing). Rows with no spare degrees of freedom get infinite
    variances; directions the data do not constrain get huge ones; never NaN.
    """

    def row(p, d, n):
        r = residual(p, d)
        jac = jax.jacfwd(residual)(p, d)
        jtj = jac.T @ jac
        dof = n - p.shape[0]
        s2 = jnp.sum(r * r) / jnp.maximum(dof, 1)
        # A tiny ridge keeps the inverse finite: directions the data do not
        # constrain get a huge variance instead of pinv's silent zero.
        ridge = 1e-12 * jnp.maximum(jnp.max(jnp.diag(jtj)), 1e-300)
        cov = s2 * jnp.linalg.inv(jtj + ridge * jnp.eye(p.shape[0]))
        bad = (dof <= 0) | ~jnp.all(jnp.isfinite(cov))
        return jnp.where(bad, jnp.diag(jnp.full(p.shape[0], jnp.inf)), cov)

    return jax.vmap(row)(params, data, n_valid)
