"""Greedy selection of capture lights from the candidates (paper §2.2).

A point is *diffuse-covered* once one selected light gives it a diffuse-only
sample, and *specular-covered* once two selected lights give it strong
specular samples (one parameter, pd, needs one observation; ps and roughness
need two). Coverages are fractions of the points the camera sees.

The paper alternates: pick the light with the largest D_p (diffuse-only count),
then the one with the largest S_q among those left, and repeat. We count only
what a light *adds* (points still needing a sample), which is the same rule on
the first pick and avoids re-picking lights that cover already-covered points;
`marginal=False` gives the paper's raw counts. Selection stops once diffuse
coverage has reached what all candidates together give and specular coverage
has passed `th1` (paper: 80 %) of its all-candidate limit and either reached
`target` of that limit or stopped rising (a light adds less than `min_gain`
of the points).

`exact_minimum` solves the same covering problem exactly as an integer program
(`scipy.optimize.milp`, HiGHS) to measure how far the greedy count is from optimal.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

__all__ = ["Selection", "coverage", "select_lights", "exact_minimum"]


@dataclass
class Selection:
    """Result of `select_lights`. `selected`: candidate indices in selection
    order; `diffuse_only_count`: how many of the first selected lights the
    diffuse parameter alone needed; coverages are fractions of seen points;
    `curve`: one dict per step (light, criterion, coverages after it)."""

    selected: list
    diffuse_only_count: int
    diffuse_coverage: float
    specular_coverage: float
    diffuse_coverage_all: float
    specular_coverage_all: float
    seen_points: int
    curve: list = field(default_factory=list)

    def to_json(self) -> dict:
        return asdict(self)


def _point_weights(n, seen, weights):
    seen = np.ones(n, bool) if seen is None else np.asarray(seen, bool)
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (n,) or not np.all(np.isfinite(w)) or np.any(w < 0):
        raise ValueError(f"weights must be (N,) finite and >= 0, got shape {w.shape}")
    w = np.where(seen, w, 0.0)
    return w, max(float(w.sum()), 1e-300), seen


def coverage(diffuse_only, strong_specular, lights, seen=None, weights=None) -> tuple[float, float]:
    """(diffuse, specular) coverage of the seen points with the light subset `lights`
    (weighted fractions when `weights` `(N,)` is given, e.g. `pixel_weight`)."""
    lights = np.asarray(lights, dtype=np.int64)
    d, s = np.asarray(diffuse_only)[:, lights], np.asarray(strong_specular)[:, lights]
    w, total, _ = _point_weights(len(d), seen, weights)
    return float(w[d.sum(1) >= 1].sum() / total), float(w[s.sum(1) >= 2].sum() / total)


def select_lights(diffuse_only, strong_specular, seen=None, th1: float = 0.8, target: float = 0.99,
                  min_gain: float = 0.0, marginal: bool = True, max_lights: int | None = None,
                  weights=None) -> Selection:
    """Greedy light selection.

    **Arguments:** `diffuse_only`, `strong_specular` `(N, K)` bool (from
    `classify`); `seen` `(N,)` bool, the points that count (default all);
    `th1`, `target`, `min_gain` as in the module docstring; `marginal` count
    only newly covered points (default) or, as the paper, all points;
    `max_lights` cap (default K); `weights` `(N,)` what each point counts for
    (default 1; `Measurability.pixel_weight` counts image pixels as the paper).

    **Returns:** `Selection`.
    """
    d = np.asarray(diffuse_only, dtype=bool)
    s = np.asarray(strong_specular, dtype=bool)
    if d.shape != s.shape or d.ndim != 2:
        raise ValueError(f"diffuse_only {d.shape} and strong_specular {s.shape} must both be (N, K)")
    n, k = d.shape
    w, total, seen = _point_weights(n, seen, weights)
    d, s = d & seen[:, None], s & seen[:, None]
    d_int, s_int = d.astype(np.int32), s.astype(np.int32)
    limit_d = float(w[d.any(1)].sum() / total)
    limit_s = float(w[s.sum(1) >= 2].sum() / total)
    max_lights = k if max_lights is None else min(max_lights, k)

    d_count = np.zeros(n, np.int32)
    s_count = np.zeros(n, np.int32)
    chosen = np.zeros(k, bool)
    selected, curve = [], []
    diffuse_done_at = 0 if limit_d == 0 else None

    def cover():
        return float(w[d_count >= 1].sum() / total), float(w[s_count >= 2].sum() / total)

    def pick(counts, matrix, need):
        gain = (w * (counts < need) if marginal else w) @ matrix
        gain[chosen] = -1.0
        best = int(np.argmax(gain))
        return best, float(gain[best])

    def take(light, criterion):
        nonlocal diffuse_done_at
        chosen[light] = True
        selected.append(light)
        d_count[:] += d_int[:, light]
        s_count[:] += s_int[:, light]
        cd, cs = cover()
        curve.append({"step": len(selected), "light": light, "criterion": criterion,
                      "diffuse_coverage": cd, "specular_coverage": cs})
        if diffuse_done_at is None and cd >= limit_d:
            diffuse_done_at = len(selected)

    rising = max(min_gain * total, 1e-12 * total)  # what a light must add to count as rising
    while len(selected) < max_lights:
        cd, cs = cover()
        diffuse_left = cd < limit_d
        specular_left = cs < target * limit_s
        if not (diffuse_left or specular_left):
            break
        progressed = False
        if diffuse_left:
            light, gain = pick(d_count, d_int, 1)
            if gain > 0:
                take(light, "diffuse")
                progressed = True
        if specular_left and len(selected) < max_lights:
            light, gain = pick(s_count, s_int, 2)
            past_th1 = cover()[1] >= th1 * limit_s
            if gain > 0 and not (past_th1 and gain < rising):
                take(light, "specular")
                progressed = True
            elif not diffuse_left:
                break  # specular coverage stopped rising past th1
        if not progressed:
            break

    cd, cs = cover()
    return Selection(
        selected=selected,
        diffuse_only_count=int(diffuse_done_at if diffuse_done_at is not None else len(selected)),
        diffuse_coverage=cd, specular_coverage=cs,
        diffuse_coverage_all=limit_d, specular_coverage_all=limit_s,
        seen_points=int(seen.sum()), curve=curve,
    )


def exact_minimum(diffuse_only, strong_specular, seen=None, target: float = 1.0,
                  time_limit: float = 60.0, weights=None) -> dict:
    """Fewest lights giving every coverable seen point one diffuse-only and two
    strong-specular samples (with `target < 1`: at least that (weighted) fraction
    of the specular limit, one binary per point), as an integer program.

    **Returns:** dict with `count`, `selected`, `status` ('optimal' or the
    solver's message) and `seconds`.
    """
    import time

    from scipy.optimize import Bounds, LinearConstraint, milp
    from scipy.sparse import csr_matrix, diags, hstack, vstack

    d = np.asarray(diffuse_only, dtype=bool)
    s = np.asarray(strong_specular, dtype=bool)
    n, k = d.shape
    w, _, seen = _point_weights(n, seen, weights)
    seen = seen & (w > 0)
    need_d = seen & d.any(1)
    can_s = seen & (s.sum(1) >= 2)
    rows_d = csr_matrix(d[need_d].astype(float))
    rows_s = csr_matrix(s[can_s].astype(float))
    t0 = time.perf_counter()
    if target >= 1.0:
        a = vstack([rows_d, rows_s])
        lower = np.r_[np.ones(rows_d.shape[0]), np.full(rows_s.shape[0], 2.0)]
        cost = np.ones(k)
        constraints = [LinearConstraint(a, lower, np.inf)]
        integrality = np.ones(k)
        bounds = Bounds(0, 1)
    else:
        # y_i = 1 where point i must be specular-covered; sum w y >= target * (limit weight).
        m = rows_s.shape[0]
        ws = w[can_s] / w[can_s].sum()
        a_s = hstack([rows_s, diags(np.full(m, -2.0))])
        a_d = hstack([rows_d, csr_matrix((rows_d.shape[0], m))])
        a_y = hstack([csr_matrix((1, k)), csr_matrix(ws[None, :])])
        constraints = [LinearConstraint(vstack([a_d, a_s, a_y]),
                                        np.r_[np.ones(rows_d.shape[0]), np.zeros(m), target - 1e-9],
                                        np.inf)]
        cost = np.r_[np.ones(k), np.zeros(m)]
        integrality = np.ones(k + m)
        bounds = Bounds(0, 1)
    res = milp(cost, constraints=constraints, integrality=integrality, bounds=bounds,
               options={"time_limit": time_limit})
    seconds = time.perf_counter() - t0
    if res.x is None:
        return {"count": None, "selected": [], "status": res.message, "seconds": seconds}
    x = np.round(res.x[:k]).astype(bool)
    return {"count": int(x.sum()), "selected": np.flatnonzero(x).tolist(),
            "status": "optimal" if res.status == 0 else res.message, "seconds": seconds}


def plot_coverage(selection: Selection, path, title: str = "") -> None:
    """Figure 8 analogue: diffuse and specular coverage against the number of selected lights."""
    from ..outputs.render import new_figure
    from ..scan.io import atomic_write

    steps = [0] + [c["step"] for c in selection.curve]
    diff = [0.0] + [100 * c["diffuse_coverage"] for c in selection.curve]
    spec = [0.0] + [100 * c["specular_coverage"] for c in selection.curve]
    fig = new_figure(figsize=(9, 3.4))
    axes = fig.subplots(1, 2, sharex=True)
    for ax, values, limit, label in (
        (axes[0], diff, selection.diffuse_coverage_all, "diffuse-only, once"),
        (axes[1], spec, selection.specular_coverage_all, "strong specular, twice"),
    ):
        ax.plot(steps, values, "o-", ms=3)
        ax.axhline(100 * limit, color="k", ls="--", lw=0.8, label="all candidates")
        ax.set_xlabel("number of selected lights")
        ax.set_ylabel("points [%]")
        ax.set_title(f"measured {label}", fontsize=9)
        ax.set_ylim(0, 100)
        ax.legend(fontsize=8, loc="lower right")
    axes[0].axvline(selection.diffuse_only_count, color="C1", lw=0.8)
    fig.suptitle(title or "Measurability against the number of selected lights", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.94))
    atomic_write(path, lambda fh: fig.savefig(fh, format="png", dpi=120))
