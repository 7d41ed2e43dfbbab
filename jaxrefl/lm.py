"""Small dense linear algebra for per-row least squares.

Every row (surface point) has its own small problem: a residual vector
`r(p, data) -> (R,)` in a handful of parameters `p` `(P,)`. The solvers that
step such problems (`local._analytic_lm_row`, or optimistix) share two pieces:

- `spd_solve`: a Cholesky solve written out over the static matrix size, fast
  under `vmap` on a CPU;
- `covariance`: the Gauss-Newton (Laplace) covariance `s^2 (J^T J)^-1` with
  `s^2 = cost / (R_valid - P)` at a solution.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

__all__ = ["covariance", "spd_solve"]


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
