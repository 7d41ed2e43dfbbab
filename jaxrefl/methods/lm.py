"""Per-row separable least squares with one nonlinear parameter.

Every row (surface point) has its own small problem: weighted residuals that
are linear in a few non-negative amplitudes and nonlinear in one parameter
`rho`. Here the amplitudes are three channel terms `u_c` (each touching one
channel, bounded `0 <= u_c <= 1`) and one shared term `v >= 0`, so for a fixed
`rho` the cost is the "arrow" quadratic

    Q(u, v) = yy - 2 sum_c u_c b1_c - 2 v b2 + sum_c u_c^2 s11_c
              + 2 v sum_c u_c s12_c + v^2 s22

and variable projection leaves a 1-D problem in `rho` (Golub & Pereyra 1973).
The pieces, all written for rows laid out along the last axis (each argument a
`(n,)` array, or a Python list of them) so that XLA on a CPU runs every formula
as one fused loop over the rows:

- `rowsum`: a written-out sum of a short list of row arrays (the channels);
- `msum`: a sum over the leading (sample) axis;
- `bounded_arrow_solve`: the exact minimiser of `Q` under the bounds;
- `projected_step_terms`: gradient and Gauss-Newton curvature of the projected
  cost in `rho` (the Schur complement over the free amplitudes);
- `gauss_newton_1d`: a safeguarded Newton iteration in `rho`;
- `spd_inverse_diagonal`: diagonal of the inverse of a small SPD matrix (for
  the Gauss-Newton covariance `s^2 (J^T J)^-1`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["rowsum", "msum", "block_sums", "bounded_arrow_solve", "projected_step_terms", "gauss_newton_1d",
           "spd_inverse_diagonal"]


def rowsum(terms):
    """`terms[0] + terms[1] + ...`, written out.

    A reduction over a short leading axis ran several times slower than the
    written-out sum on XLA-CPU, which fuses the latter into one loop.
    """
    total = terms[0]
    for t in terms[1:]:
        total = total + t
    return total


#: Samples summed written out per step of `block_sums`' loop.
SAMPLE_BLOCK = 8


def msum(x):
    """Sum of `x` `(M, ...)` over its leading (sample) axis: written out for fewer than two
    blocks of samples (faster on XLA-CPU), a reduction beyond (a program of fixed size)."""
    return rowsum(list(x)) if x.shape[0] < 2 * SAMPLE_BLOCK else jnp.sum(x, axis=0)


def block_sums(integrands, arrays, block: int = SAMPLE_BLOCK):
    """`[sum_j f_j ...]`: the sums over the leading (sample) axis of the arrays `integrands`
    returns from slices of `arrays` (a pytree of `(M, ...)` arrays), `block` samples at a
    time: written out within a block (XLA-CPU fuses that into one loop over the rows,
    several times faster than a reduction of a short axis), a loop over the blocks (so the
    compiled program does not grow with M)."""
    m = jax.tree_util.tree_leaves(arrays)[0].shape[0]

    def part(start, size):
        piece = jax.tree_util.tree_map(lambda a: jax.lax.dynamic_slice_in_dim(a, start, size, 0), arrays)
        return [rowsum(list(v)) for v in integrands(piece)]

    blocks, rest = divmod(m, block)
    if blocks <= 1:
        return part(0, m)
    total = jax.lax.fori_loop(1, blocks, lambda i, acc: [a + p for a, p in zip(acc, part(i * block, block))],
                              part(0, block))
    return [a + p for a, p in zip(total, part(blocks * block, rest))] if rest else total


def bounded_arrow_solve(s11, s11_inv, s12, s22, b1, b2):
    """Exact minimiser of the arrow quadratic `Q` over `0 <= u_c <= 1`, `v >= 0`.

    **Arguments:** `s11` (`>= 0`), `s11_inv` (`1 / s11`, 0 where `s11` is 0),
    `s12`, `b1`: lists of three `(n,)` arrays (per channel); `s22`, `b2`: `(n,)`.

    **Returns:** `(u, v, free)`: `u` a list of three `(n,)` arrays, `v` `(n,)`,
    `free` a list of three `(n,)` bool (`u_c` strictly inside its bounds).

    For a fixed `v` each `u_c` is its clipped unconstrained value, so the
    derivative of the reduced cost, `f(v) = s22 v - b2 + sum_c s12_c u_c(v)`,
    is nondecreasing and piecewise linear with a breakpoint where a channel
    reaches a bound. Evaluating `f` at the (at most seven) breakpoints brackets
    its root on a linear piece, which interpolation then finds exactly.
    (Divisions are few and by precomputed reciprocals: XLA-CPU will not fuse a
    division into several consumers, so each shared one costs a pass.)
    """

    def raw(t):
        return [(b1[c] - s12[c] * t) * s11_inv[c] for c in range(3)]

    def f(t):
        return s22 * t - b2 + rowsum([s12[c] * jnp.clip(r, 0.0, 1.0) for c, r in enumerate(raw(t))])

    zero = jnp.zeros_like(s22)
    ts = [zero]
    for c in range(3):
        ok = s12[c] > 1e-300 * s11[c]
        inv = jnp.where(ok, 1.0 / jnp.where(ok, s12[c], 1.0), 0.0)
        ts += [jnp.maximum(b1[c] * inv, 0.0), jnp.maximum((b1[c] - s11[c]) * inv, 0.0)]
    fs = [f(t) for t in ts]
    t_lo, f_lo = zero, fs[0]
    t_hi, f_hi = jnp.full_like(s22, jnp.inf), jnp.full_like(s22, jnp.inf)
    for t, ft in zip(ts, fs):
        below = ft < 0
        up = below & (t >= t_lo)
        t_lo, f_lo = jnp.where(up, t, t_lo), jnp.where(up, ft, f_lo)
        down = ~below & (t < t_hi)
        t_hi, f_hi = jnp.where(down, t, t_hi), jnp.where(down, ft, f_hi)
    # On [t_lo, t_hi] f is linear; past every breakpoint (t_hi = inf) its slope is s22.
    bracketed = jnp.isfinite(t_hi)
    rise = jnp.where(bracketed, f_hi - f_lo, s22)
    run = jnp.where(bracketed, t_hi - t_lo, 1.0)
    # v = t_lo - f_lo run / rise, written as one final division: XLA-CPU keeps a division
    # (not a select) as the root of a fused loop, so v is computed once for its readers.
    none = (fs[0] >= 0) | ~(rise > 0)
    v = jnp.where(none, 0.0, t_lo * rise - f_lo * run) / jnp.where(none, 1.0, rise)
    r = raw(v)
    return [jnp.clip(x, 0.0, 1.0) for x in r], v, [(x > 0) & (x < 1) for x in r]


def projected_step_terms(s11_inv, s12, s22, u, v, free, s1d, s2d, sdd, b2d):
    """Gradient `g` and Gauss-Newton curvature `h` of half the projected cost in `rho`.

    The model's derivative in `rho` is `v d_j` (the shared term's shape `b_j`
    times its log-derivative), with the weighted sums `s1d_c = sum w_c a_j d_j`,
    `s2d = sum w b_j d_j`, `sdd = sum w d_j^2`, `b2d = sum w y_j d_j`. At the
    bounded optimum (`u`, `v`, `free`) the gradient is the envelope
    `-v (b2d - sum_c u_c s1d_c - v s2d)`; the curvature is the Schur complement
    of the Gauss-Newton matrix over the free amplitudes (bound ones are held).

    **Returns:** `(g, h)`, each `(n,)`, `h >= 0`.
    """
    g = -v * (b2d - rowsum([s1d[c] * u[c] for c in range(3)]) - v * s2d)
    inv = [jnp.where(free[c], s11_inv[c], 0.0) for c in range(3)]
    v1 = [v * s1d[c] for c in range(3)]
    schur = s22 - rowsum([s12[c] * s12[c] * inv[c] for c in range(3)])
    cross = v * s2d - rowsum([s12[c] * v1[c] * inv[c] for c in range(3)])
    shared = jnp.where((v > 0) & (schur > 0), cross * cross / jnp.where(schur > 0, schur, 1.0), 0.0)
    h = v * v * sdd - rowsum([v1[c] * v1[c] * inv[c] for c in range(3)]) - shared
    return g, jnp.maximum(h, 0.0)


def gauss_newton_1d(evaluate, rho0, steps, lo, hi, radius=0.5, tol=1e-9):
    """Safeguarded Newton iteration on a per-row 1-D cost, at most `steps` steps.

    **Arguments:** `evaluate(rho) -> (cost, g, h)` (each `(n,)`: the cost, half
    its derivative and half its Gauss-Newton second derivative); `rho0` `(n,)`
    start; `steps` static count; `lo <= rho <= hi` bounds; `radius` the first
    trust radius; `tol`: the iteration ends early once no row would move by more.

    **Returns:** `(rho, cost)`, each `(n,)`.

    The first step is Gauss-Newton's; later ones use the secant of `g` over the
    last kept step as the curvature (where residuals are large Gauss-Newton
    underestimates it and its steps overshoot back and forth), and go to the
    trust radius where that curvature is not positive (flat and concave
    stretches, where Newton steps crawl). A step is kept only where it lowers
    the cost; a kept step at the radius doubles it, a refused one sets it to a
    quarter of the step. The cost never increases and a converged row stays put.
    """
    rho0 = jnp.clip(rho0, lo, hi)
    cost0, g0, h0 = evaluate(rho0)

    def trial_of(state):
        _, rho, _, g, curv, trust = state
        newton = -g / jnp.where(curv > 0, curv, 1.0)
        step = jnp.where(curv > 0, jnp.clip(newton, -trust, trust), -jnp.sign(g) * trust)
        return jnp.clip(rho + jnp.where(jnp.isfinite(step), step, 0.0), lo, hi)

    def unfinished(state):
        return (state[0] < steps) & jnp.any(jnp.abs(trial_of(state) - state[1]) > tol)

    def body(state):
        k, rho, cost, g, curv, trust = state
        trial = trial_of(state)
        cost_t, g_t, _ = evaluate(trial)
        moved = trial - rho
        ok = jnp.isfinite(cost_t) & (cost_t < cost) & (moved != 0)
        secant = (g_t - g) / jnp.where(ok, moved, 1.0)
        at_edge = jnp.abs(moved) >= 0.99 * trust
        keep = lambda new, old: jnp.where(ok, new, old)  # noqa: E731
        trust = jnp.where(ok, jnp.where(at_edge, 2.0 * trust, trust), 0.1 * jnp.abs(moved))
        return k + 1, keep(trial, rho), keep(cost_t, cost), keep(g_t, g), keep(secant, curv), trust

    state = (0, rho0, cost0, g0, h0, jnp.full_like(rho0, radius))
    _, rho, cost, *_ = jax.lax.while_loop(unfinished, body, state)
    return rho, cost


def spd_inverse_diagonal(a, ridge=1e-12):
    """Diagonal of `(a + ridge max(diag a) I)^-1` for a small symmetric positive
    semi-definite `a`, one matrix per row.

    **Arguments:** `a`: `P x P` nested lists of `(n,)` arrays (only `a[i][j]`,
    `j <= i`, is read); `ridge`: relative ridge, so that directions the data do
    not constrain get a huge variance rather than a division by zero.

    **Returns:** a list of `P` `(n,)` arrays. Cholesky and the triangular
    inverse are written out over the static size: every entry is one
    elementwise operation over all rows.
    """
    n = len(a)
    top = a[0][0]
    for i in range(1, n):
        top = jnp.maximum(top, a[i][i])
    eps = ridge * jnp.maximum(top, 1e-300)
    low = [[None] * n for _ in range(n)]
    for i in range(n):
        for j in range(i + 1):
            acc = a[i][j] + (eps if i == j else 0.0) - rowsum([low[i][k] * low[j][k] for k in range(j)] or [0.0])
            low[i][j] = jnp.sqrt(jnp.maximum(acc, 1e-300)) if i == j else acc / low[j][j]
    # inv(L) column by column: (L^-1)_ij = -sum_k L_ik (L^-1)_kj / L_ii.
    inv = [[None] * n for _ in range(n)]
    for j in range(n):
        inv[j][j] = 1.0 / low[j][j]
        for i in range(j + 1, n):
            inv[i][j] = -rowsum([low[i][k] * inv[k][j] for k in range(j, i)]) / low[i][i]
    # (A^-1)_jj = sum_i (L^-1)_ij^2.
    return [rowsum([inv[i][j] * inv[i][j] for i in range(j, n)]) for j in range(n)]
