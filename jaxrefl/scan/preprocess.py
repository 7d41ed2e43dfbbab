"""Range-data preprocessing (paper §2.1): outlier removal, normals by adaptive local
quadratic surface fitting (Yokoya & Levine 1989), range image -> mesh.

A Cyberware-style rangefinder rotating about the y axis measures, for every head
angle `theta` (from +z toward +x) and height `y`, the radius `r(theta, y)` of the
first surface point its ray meets: a `RangeImage` on a cylindrical grid, row 0 at
the top. Everything here is host-side NumPy, vectorised over pixels (or
vertices); the only Python loops run over the `window**2` positions of a window
(or the `k` neighbourhoods of a vertex).

Window selection. Yokoya & Levine fit a quadratic in every `w x w` window that
contains a pixel and keep the fit with the smallest residual, so that a fit never
straddles a depth discontinuity. Taken literally (`select="residual"`) the choice
among windows of a smooth surface is decided by noise alone, and a window whose
corner holds the pixel estimates the slope there with several times the variance
of the centred window. The default, `select="variance"`, keeps the same rule but
ranks windows by the estimated variance of the fitted slope *at the pixel*,
`max(sigma_hat^2, floor) * g^T (A^T A)^{-1} g`, where `floor` is twice the median
`sigma_hat^2` of all fits (below it a residual is noise, and the estimate of
`sigma_hat^2` from ~20 residuals is itself uncertain by ~30 %): a window
straddling a discontinuity has a huge `sigma_hat^2` and loses as before, while on
smooth ground the centred window wins. Both rules are measured in
`benchmarks/normals_report.py` (measurements: `benchmarks/RESULTS_notes.md`,
`benchmarks/RESULTS_normals.md`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..geometry.mesh import area_normal_sums

__all__ = [
    "angular_error_deg",
    "RangeImage",
    "face_averaged_normals",
    "mesh_quadratic_normals",
    "quadratic_fit",
    "range_image_to_mesh",
    "remove_outliers",
]

_MAD = 1.4826  # MAD -> standard deviation for Gaussian data
_NPARAM = 6  # 1, u, v, u^2, uv, v^2
_COND_MIN = 1e-10  # smallest accepted eigenvalue ratio of a normal matrix
_BIG = 1e300  # ranking key of a fit with no degrees of freedom left (exact fit)
_SELECT = ("variance", "residual")
# Residual variances below this multiple of the median over all fits count as noise:
# about the 99th percentile of sigma_hat^2 / sigma^2 for ~20 degrees of freedom.
_FLOOR_FACTOR = 2.0


# -- range images ------------------------------------------------------------------


@dataclass(frozen=True, eq=False)  # eq=False: field-wise == on arrays is ambiguous
class RangeImage:
    """A range image on the scanner's cylindrical grid.

    **Fields:** `r` `(H, W)` float64 radius from the y axis [m], NaN where the ray
    had no return; `theta` `(W,)` head angle of each column [rad], from +z toward
    +x, strictly increasing, spanning less than `2 pi`; `y` `(H,)` height of each
    row [m], strictly decreasing (row 0 at the top).
    """

    r: np.ndarray
    theta: np.ndarray
    y: np.ndarray

    def __post_init__(self) -> None:
        r = _float_array("r", self.r)
        theta = _float_array("theta", self.theta)
        y = _float_array("y", self.y)
        if r.ndim != 2 or r.shape[0] < 1 or r.shape[1] < 1:
            raise ValueError(f"RangeImage.r: must be a 2-D (H, W) array, got shape {r.shape}")
        h, w = r.shape
        if theta.shape != (w,):
            raise ValueError(f"RangeImage.theta: must have shape ({w},) to match r, "
                             f"got {theta.shape}")
        if y.shape != (h,):
            raise ValueError(f"RangeImage.y: must have shape ({h},) to match r, got {y.shape}")
        if np.isinf(r).any():
            raise ValueError("RangeImage.r: must be finite or NaN (no return), found inf")
        if np.any(r[np.isfinite(r)] < 0):
            raise ValueError(f"RangeImage.r: must be >= 0, found {np.nanmin(r)}")
        if not np.isfinite(theta).all():
            raise ValueError("RangeImage.theta: must be finite")
        if w > 1 and not np.all(np.diff(theta) > 0):
            raise ValueError("RangeImage.theta: must be strictly increasing")
        if theta[-1] - theta[0] >= 2 * np.pi:
            raise ValueError("RangeImage.theta: must span less than 2 pi, "
                             f"spans {theta[-1] - theta[0]}")
        if not np.isfinite(y).all():
            raise ValueError("RangeImage.y: must be finite")
        if h > 1 and not np.all(np.diff(y) < 0):
            raise ValueError("RangeImage.y: must be strictly decreasing (row 0 at the top)")
        object.__setattr__(self, "r", r)
        object.__setattr__(self, "theta", theta)
        object.__setattr__(self, "y", y)

    @property
    def shape(self) -> tuple[int, int]:
        """`(H, W)`."""
        return self.r.shape

    @property
    def dtheta(self) -> float:
        """Median column spacing [rad] (`2 pi` for a single column)."""
        return float(np.median(np.diff(self.theta))) if len(self.theta) > 1 else 2 * np.pi

    @property
    def dy(self) -> float:
        """Median row spacing [m], positive (1 for a single row)."""
        return float(np.median(-np.diff(self.y))) if len(self.y) > 1 else 1.0

    @property
    def full_circle(self) -> bool:
        """Do the columns cover the whole turn, so that theta wraps around?
        True when the gap from the last column back to the first is within
        half a column spacing of the median spacing."""
        w = len(self.theta)
        if w < 3:
            return False
        gap = self.theta[0] + 2 * np.pi - self.theta[-1]
        return bool(abs(gap - self.dtheta) < 0.5 * self.dtheta)

    @property
    def valid(self) -> np.ndarray:
        """`(H, W)` bool: the pixel has a return."""
        return np.isfinite(self.r)

    def points(self) -> np.ndarray:
        """`(H, W, 3)` points `(r sin theta, y, r cos theta)` [m]; NaN where no return."""
        s, c = np.sin(self.theta), np.cos(self.theta)
        yy = np.broadcast_to(self.y[:, None], self.r.shape)
        return np.stack([self.r * s, np.where(self.valid, yy, np.nan), self.r * c], axis=-1)

    def with_r(self, r) -> RangeImage:
        """The same grid with new radii `r` `(H, W)` [m] (NaN = no return)."""
        return RangeImage(r, self.theta, self.y)


def _float_array(name: str, x) -> np.ndarray:
    try:
        a = np.array(x, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"RangeImage.{name}: must be a float array ({e})") from None
    return a


def _check_image(img) -> RangeImage:
    if not isinstance(img, RangeImage):
        raise ValueError(f"img: must be a RangeImage, got {type(img).__name__}")
    return img


def _is_int(x, lo: int) -> bool:
    return not isinstance(x, bool) and isinstance(x, (int, np.integer)) and x >= lo


def _check_window(window) -> int:
    if not _is_int(window, 3) or window % 2 == 0:
        raise ValueError(f"window: must be an odd integer >= 3, got {window!r}")
    return int(window)


def _check_positive(name: str, x) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: must be a positive number, got {x!r}") from None
    if not np.isfinite(v) or v <= 0:
        raise ValueError(f"{name}: must be a positive finite number, got {x!r}")
    return v


# -- grid helpers ----------------------------------------------------------------


def _pad(a: np.ndarray, h: int, wrap: bool, fill) -> np.ndarray:
    """Pad the first two axes by `h`: rows with `fill`, columns periodic if `wrap`."""
    extra = [(0, 0)] * (a.ndim - 2)
    if wrap:
        a = np.pad(a, [(0, 0), (h, h)] + extra, mode="wrap")
    else:
        a = np.pad(a, [(0, 0), (h, h)] + extra, constant_values=fill)
    return np.pad(a, [(h, h), (0, 0)] + extra, constant_values=fill)


def _shift(padded: np.ndarray, h: int, di: int, dj: int, shape) -> np.ndarray:
    """`out[i, j] = a[i + di, j + dj]` from `padded = _pad(a, h, ...)`."""
    H, W = shape
    return padded[h + di: h + di + H, h + dj: h + dj + W]


def _extended_axes(img: RangeImage, h: int, wrap: bool):
    """Column angles and row heights extended by `h` on each side (unwrapped when
    periodic, extrapolated otherwise; extrapolated values are only ever masked)."""
    W, H = len(img.theta), len(img.y)
    j = np.arange(-h, W + h)
    if wrap:
        theta_ext = img.theta[j % W] + 2 * np.pi * np.floor_divide(j, W)
    else:
        theta_ext = np.interp(j, np.arange(W), img.theta)
        theta_ext = np.where(j < 0, img.theta[0] + j * img.dtheta, theta_ext)
        theta_ext = np.where(j >= W, img.theta[-1] + (j - W + 1) * img.dtheta, theta_ext)
    i = np.arange(-h, H + h)
    y_ext = np.interp(i, np.arange(H), img.y)
    y_ext = np.where(i < 0, img.y[0] - i * img.dy, y_ext)
    y_ext = np.where(i >= H, img.y[-1] - (i - H + 1) * img.dy, y_ext)
    return theta_ext, y_ext


def _offsets(h: int):
    return [(di, dj) for di in range(-h, h + 1) for dj in range(-h, h + 1)]


def _windows(a: np.ndarray, h: int, wrap: bool) -> np.ndarray:
    """`(H, W, (2h+1)^2)` samples of each centred window, NaN outside the image."""
    p = _pad(a, h, wrap, np.nan)
    return np.stack([_shift(p, h, di, dj, a.shape) for di, dj in _offsets(h)], axis=-1)


def _nanmedian_last(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Median over the last axis ignoring NaN, and the count of finite values
    (median NaN where none)."""
    s = np.sort(x, axis=-1)  # NaN sort last
    n = np.isfinite(x).sum(-1)
    lo = np.take_along_axis(s, np.maximum((n - 1) // 2, 0)[..., None], -1)[..., 0]
    hi = np.take_along_axis(s, np.maximum(n // 2, 0)[..., None], -1)[..., 0]
    return np.where(n > 0, 0.5 * (lo + hi), np.nan), n


# -- outliers ----------------------------------------------------------------------


def remove_outliers(img: RangeImage, window: int = 5, k: float = 4.0,
                    min_scale: float = 5e-5) -> tuple[RangeImage, np.ndarray]:
    """Remove isolated spikes from a range image.

    A return is an outlier when it disagrees by more than `k` robust scales with
    *every* `window x window` window that contains it (the adaptive idea of the
    fits: a pixel at a depth edge or a corner agrees with the windows on its own
    side, a spike with none). A window's reference is a robust plane: its slopes
    along theta and y are the medians of the window's neighbour differences, its
    level the median of the detrended samples (a plain median lets spikes hide
    among a steep slope's own values at grazing incidence). A window's scale is
    `1.4826 x` the median of `|r - level|` over its pixels, each against the
    plane of its own centred window, floored at `min_scale` [m] (about the
    quantisation step; it keeps noise-free or heavily quantised data from being
    flagged). Windows with fewer than `max(3, window**2 // 4)` returns are not
    used; a return with no usable window is unsupported and removed too.

    **Arguments:** `img` RangeImage; `window` odd >= 3; `k` > 0; `min_scale` [m] > 0.

    **Returns:** `(cleaned, removed)`: the image with removed returns set to NaN,
    and `(H, W)` bool, True where a return was removed.
    """
    img = _check_image(img)
    window = _check_window(window)
    k = _check_positive("k", k)
    min_scale = _check_positive("min_scale", min_scale)
    zmin = _median_z(img, window // 2, img.full_circle, min_scale)
    removed = img.valid & ~(zmin <= k)
    return img.with_r(np.where(removed, np.nan, img.r)), removed


def _offset_coordinates(img: RangeImage, h: int, wrap: bool):
    """Grid-unit coordinates of the samples at each offset from a window centre:
    `S[dj]` `(W,)` = `(theta[j + dj] - theta[j]) / dtheta` (unwrapped across the
    seam) and `T[di]` `(H,)` = `(y[i + di] - y[i]) / dy`, for `|d| <= h`."""
    theta_ext, y_ext = _extended_axes(img, h, wrap)
    H, W = img.shape
    S = {dj: (theta_ext[h + dj: h + dj + W] - img.theta) / img.dtheta for dj in range(-h, h + 1)}
    T = {di: (y_ext[h + di: h + di + H] - img.y) / img.dy for di in range(-h, h + 1)}
    return S, T


def _median_z(img: RangeImage, h: int, wrap: bool, min_scale: float) -> np.ndarray:
    """`(H, W)` smallest |r - window plane| / window scale over the windows
    holding each pixel (inf where none is usable).

    The window plane is robust: slopes are the medians of the window's
    neighbour differences along theta and y, its level the median of the
    detrended samples (on steep, grazing ground a plain median lets spikes hide
    among the slope's own values)."""
    shape, r = img.shape, img.r
    S, T = _offset_coordinates(img, max(h, 1), wrap)
    rp = _pad(r, max(h, 1), wrap, np.nan)
    ds = (_shift(rp, max(h, 1), 0, 1, shape) - r) / S[1][None, :]
    dt = (_shift(rp, max(h, 1), 1, 0, shape) - r) / T[1][:, None]
    slope_s, _ = _nanmedian_last(_windows(ds, h, wrap))
    slope_t, _ = _nanmedian_last(_windows(dt, h, wrap))
    slope_s, slope_t = np.nan_to_num(slope_s), np.nan_to_num(slope_t)
    rp = _pad(r, h, wrap, np.nan)
    offs = _offsets(h)
    detrended = np.stack([_shift(rp, h, di, dj, shape)
                          - slope_s * S[dj][None, :] - slope_t * T[di][:, None]
                          for di, dj in offs], axis=-1)
    level, n = _nanmedian_last(detrended)
    scale, _ = _nanmedian_last(np.abs(_windows(r - level, h, wrap)))
    scale = np.maximum(_MAD * np.nan_to_num(scale, nan=0.0), min_scale)
    support = n >= max(3, (2 * h + 1) ** 2 // 4)
    level = np.where(support, level, np.nan)
    zmin = np.full(shape, np.inf)
    with np.errstate(invalid="ignore"):
        for di, dj in offs:
            # The window centred at (i - di, j - dj) holds pixel (i, j); its plane there:
            pred = level + slope_s * S[dj][None, :] + slope_t * T[di][:, None]
            z = np.abs(r - _shift(_pad(pred, h, wrap, np.nan), h, -di, -dj, shape))
            zmin = np.fmin(zmin, z / _shift(_pad(scale, h, wrap, 1.0), h, -di, -dj, shape))
    return zmin


# -- quadratic fits on the grid ------------------------------------------------------


def _basis(s, t):
    """`(..., 6)` quadratic basis at local coordinates `s, t`."""
    s, t = np.broadcast_arrays(s, t)
    return np.stack([np.ones_like(s), s, t, s * s, s * t, t * t], axis=-1)


_EXP = ((0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2))  # monomial exponents of the basis
_MOM = tuple((p, q) for p in range(5) for q in range(5 - p))  # s^p t^q needed by A^T A
# Entries of the inverse normal matrix that the slope variances need (upper triangle).
_VAR_IDX = ((1, 1), (3, 3), (4, 4), (1, 3), (1, 4), (3, 4),
            (2, 2), (5, 5), (2, 4), (2, 5), (4, 5))


def _assemble(mom: dict, rmom: dict):
    """Normal matrix `(..., 6, 6)` and right-hand side `(..., 6)` from the moments
    `mom[(p, q)] = sum w s^p t^q` and `rmom[(p, q)] = sum w z s^p t^q`."""
    M = np.stack([np.stack([mom[(pa + pb, qa + qb)] for pb, qb in _EXP], -1)
                  for pa, qa in _EXP], -2)
    b = np.stack([rmom[e] for e in _EXP], -1)
    return M, b


def _noise_floor(sigma2: np.ndarray) -> float:
    """`_FLOOR_FACTOR x` the median residual variance of all usable fits: the
    variance below which fits are taken as equally good (noise alone)."""
    s = sigma2[np.isfinite(sigma2)]
    return _FLOOR_FACTOR * float(np.median(s)) if len(s) else 0.0


def _evaluate(c, s, t):
    """Quadratic with coefficients `c` (sequence of 6 arrays) at `s, t`: value
    and the two first derivatives."""
    val = c[0] + s * (c[1] + c[3] * s + c[4] * t) + t * (c[2] + c[5] * t)
    ds = c[1] + 2 * c[3] * s + c[4] * t
    dt = c[2] + c[4] * s + 2 * c[5] * t
    return val, ds, dt


def _slope_variances(m, s, t):
    """`g_s^T Minv g_s` and `g_t^T Minv g_t` for the basis gradients at `s, t`,
    with `m[(i, j)]` the needed entries of the symmetric inverse normal matrix."""
    vs = (m[(1, 1)] + 4 * s * s * m[(3, 3)] + t * t * m[(4, 4)]
          + 4 * s * m[(1, 3)] + 2 * t * m[(1, 4)] + 4 * s * t * m[(3, 4)])
    vt = (m[(2, 2)] + s * s * m[(4, 4)] + 4 * t * t * m[(5, 5)]
          + 2 * s * m[(2, 4)] + 4 * t * m[(2, 5)] + 4 * s * t * m[(4, 5)])
    return vs, vt


def _solve_batched(M: np.ndarray, ok: np.ndarray):
    """Inverse of each well-conditioned `(..., 6, 6)` SPD matrix; `ok` is updated
    with the conditioning test (eigenvalue ratio >= 1e-10) and the others get I."""
    ev = np.linalg.eigvalsh(np.where(ok[..., None, None], M, np.eye(_NPARAM)))
    ok = ok & (ev[..., 0] > _COND_MIN * ev[..., -1]) & (ev[..., -1] > 0)
    Minv = np.linalg.inv(np.where(ok[..., None, None], M, np.eye(_NPARAM)))
    return Minv, ok


def _grid_fits(img: RangeImage, h: int, wrap: bool, min_samples: int):
    """Least-squares quadratic of r over the window centred at every pixel.

    Local coordinates are grid units, `s = (theta - theta_c) / dtheta` and
    `t = (y - y_c) / dy`: an affine rescaling of the arc-length coordinates
    `u = r0 (theta - theta_c)`, `v = y - y_c`, so the fitted surface is the same
    and the normal matrices are well scaled.

    **Returns:** `fields` dict of `(H, W)` arrays: `c0..c5` coefficients, the
    inverse normal matrix entries `_VAR_IDX`, `sigma2` unbiased residual
    variance [m^2] (inf for an exact fit, NaN where no usable fit).
    """
    shape = img.shape
    H, W = shape
    S, T = _offset_coordinates(img, h, wrap)
    rp = _pad(img.r, h, wrap, np.nan)
    mom = {e: np.zeros(shape) for e in _MOM}
    rmom = {e: np.zeros(shape) for e in _EXP}
    n = np.zeros(shape, dtype=np.int64)
    for di, dj in _offsets(h):
        rv = _shift(rp, h, di, dj, shape)
        m = np.isfinite(rv)
        mf = m.astype(np.float64)
        rz = np.where(m, rv, 0.0)
        sp = [np.ones(W), S[dj], S[dj] ** 2, S[dj] ** 3, S[dj] ** 4]
        tq = [np.ones(H), T[di], T[di] ** 2, T[di] ** 3, T[di] ** 4]
        for p, q in _MOM:
            mom[(p, q)] += mf * np.outer(tq[q], sp[p])
        for p, q in _EXP:
            rmom[(p, q)] += rz * np.outer(tq[q], sp[p])
        n += m
    M, b = _assemble(mom, rmom)
    Minv, ok = _solve_batched(M, n >= min_samples)
    coef = np.einsum("...ij,...j->...i", Minv, b)
    c = [np.ascontiguousarray(coef[..., i]) for i in range(_NPARAM)]
    ssr = np.zeros(shape)
    for di, dj in _offsets(h):
        rv = _shift(rp, h, di, dj, shape)
        m = np.isfinite(rv)
        fit, _, _ = _evaluate(c, S[dj][None, :], T[di][:, None])
        ssr += np.where(m, np.where(m, rv, 0.0) - fit, 0.0) ** 2
    dof = n - _NPARAM
    sigma2 = np.where(dof > 0, ssr / np.maximum(dof, 1), np.inf)
    fields = {f"c{i}": c[i] for i in range(_NPARAM)}
    fields.update({ij: np.ascontiguousarray(Minv[..., ij[0], ij[1]]) for ij in _VAR_IDX})
    fields["sigma2"] = np.where(ok, sigma2, np.nan)
    return fields


def quadratic_fit(img: RangeImage, window: int = 5, adaptive: bool = True,
                  min_samples: int = 6, select: str = "variance"):
    """Denoised points and normals by local quadratic fits to `r(theta, y)`.

    In every `window x window` window, `r` is fitted by least squares as a
    quadratic in the local arc-length / height coordinates (samples without a
    return are left out; a fit needs `min_samples >= 6` returns and a
    well-conditioned normal matrix). With `adaptive=False` a pixel uses the window
    centred on it; with `adaptive=True` every window that contains it competes and
    the best one is kept (`select`: `"variance"`, smallest estimated variance of
    the fitted slope at the pixel, default; `"residual"`, smallest RMS residual,
    Yokoya & Levine's rule as written; see the module docstring). The fitted `r`
    at the pixel gives the point, its derivatives the normal
    `P_theta x P_y = (r sin - r_theta cos, -r r_y, r cos + r_theta sin)`, which
    points away from the axis on a convex surface. Theta wraps around when the
    image covers the full circle.

    **Arguments:** `img` RangeImage; `window` odd >= 3; `adaptive` bool;
    `min_samples` >= 6; `select` `"variance"` or `"residual"`.

    **Returns:** `points` `(H, W, 3)` [m], `normals` `(H, W, 3)` unit outward,
    `valid` `(H, W)` bool, `residual` `(H, W)` RMS residual of the chosen fit
    [m] (`sqrt(SSR / (n - 6))`, 0 for an exact fit of 6 samples). Pixels without
    a return, or with no usable fit, have `valid` False and NaN ("no return") in
    the other three.
    """
    img = _check_image(img)
    window = _check_window(window)
    if not _is_int(min_samples, 6):
        raise ValueError(f"min_samples: must be an integer >= 6, got {min_samples!r}")
    if select not in _SELECT:
        raise ValueError(f"select: must be one of {_SELECT}, got {select!r}")
    h, wrap, shape = window // 2, img.full_circle, img.shape
    H, W = shape
    fields = _grid_fits(img, h, wrap, int(min_samples))
    padded = {key: _pad(val, h, wrap, np.nan) for key, val in fields.items()}
    theta_ext, y_ext = _extended_axes(img, h, wrap)

    r_pix = img.r
    arc = np.where(np.isfinite(r_pix) & (r_pix > 0), r_pix, 1.0) * img.dtheta  # metres per column
    floor = _noise_floor(fields["sigma2"])
    best_key = np.full(shape, np.inf)
    best = [np.full(shape, np.nan) for _ in range(4)]  # r, r_s, r_t, sigma2
    for a, bj in (_offsets(h) if adaptive else [(0, 0)]):
        # The window centred at (i - a, j - bj) holds pixel (i, j) at local (s, t).
        f = {key: _shift(val, h, -a, -bj, shape) for key, val in padded.items()}
        s = ((img.theta - theta_ext[h - bj: h - bj + W]) / img.dtheta)[None, :]
        t = ((img.y - y_ext[h - a: h - a + H]) / img.dy)[:, None]
        c = [f[f"c{i}"] for i in range(_NPARAM)]
        val, ds, dt = _evaluate(c, s, t)
        sig2 = f["sigma2"]
        if select == "variance":
            vs, vt = _slope_variances(f, s, t)
            key = np.maximum(sig2, floor) * (vs / arc**2 + vt / img.dy**2)
        else:
            key = sig2.copy()
        key = np.where(np.isinf(sig2), _BIG, key)
        key = np.where(np.isnan(key), np.inf, key)  # no usable fit
        better = key < best_key
        best_key = np.where(better, key, best_key)
        for dst, src in zip(best, (val, ds, dt, sig2)):
            dst[better] = src[better]

    r_fit, r_th, r_y, sig2 = best[0], best[1] / img.dtheta, best[2] / img.dy, best[3]
    sn, cs = np.sin(img.theta)[None, :], np.cos(img.theta)[None, :]
    nrm = np.stack([r_fit * sn - r_th * cs, -r_fit * r_y, r_fit * cs + r_th * sn], axis=-1)
    length = np.linalg.norm(nrm, axis=-1)
    with np.errstate(invalid="ignore"):
        valid = img.valid & np.isfinite(best_key) & np.isfinite(length) & (length > 0) & (r_fit > 0)
    normals = np.where(valid[..., None], nrm / np.where(valid, length, 1.0)[..., None], np.nan)
    yy = np.broadcast_to(img.y[:, None], shape)
    points = np.where(valid[..., None], np.stack([r_fit * sn, yy, r_fit * cs], axis=-1), np.nan)
    sig2 = np.where(valid & np.isfinite(sig2), sig2, 0.0)
    residual = np.where(valid, np.sqrt(sig2), np.nan)
    return points, normals, valid, residual


# -- meshes ------------------------------------------------------------------------


def range_image_to_mesh(img: RangeImage, max_jump: float | None = None):
    """Grid triangulation of a range image.

    Every quad of neighbouring pixels whose four corners have returns becomes two
    triangles (split along its shorter diagonal), wrapping around in theta when
    the image covers the full circle; quads with a radius step larger than
    `max_jump` [m] between two adjacent corners are skipped (depth
    discontinuities). Default `max_jump`: 4x the median distance between
    neighbouring returns. Faces are wound so that right-hand normals point away
    from the axis (outward on a convex surface). Pixels in no face are dropped.

    **Returns:** `vertices` `(P, 3)` [m], `faces` `(F, 3)` int64, `pixel` `(P, 2)`
    int64 (row, column) of each vertex.
    """
    img = _check_image(img)
    H, W = img.shape
    pts = img.points()
    valid = img.valid
    wrap = img.full_circle
    r = img.r
    if max_jump is None:
        d = [np.linalg.norm(pts[1:] - pts[:-1], axis=-1).ravel(),
             np.linalg.norm(pts[:, 1:] - pts[:, :-1], axis=-1).ravel()]
        d = np.concatenate(d)
        d = d[np.isfinite(d)]
        max_jump = 4.0 * float(np.median(d)) if len(d) else np.inf
        if max_jump == 0:
            max_jump = np.inf
    else:
        max_jump = _check_positive("max_jump", max_jump)
    cols = np.arange(W if wrap else W - 1)
    j1 = (cols + 1) % W
    rows = np.arange(H - 1)
    ii, jj = np.meshgrid(rows, cols, indexing="ij")
    jn = j1[None, :].repeat(len(rows), 0)
    # Quad corners a b / c d: +column = +theta, +row = -y.
    a, b, c, d = (ii, jj), (ii, jn), (ii + 1, jj), (ii + 1, jn)
    with np.errstate(invalid="ignore"):
        quad = valid[a] & valid[b] & valid[c] & valid[d]
        for p, q in ((a, b), (c, d), (a, c), (b, d)):
            quad &= np.abs(r[p] - r[q]) <= max_jump
    idx = np.full((H, W), -1, dtype=np.int64)
    flat = lambda p: p[0] * W + p[1]  # noqa: E731
    fa, fb, fc, fd = (flat(p)[quad] for p in (a, b, c, d))
    P = pts.reshape(-1, 3)
    ad = np.linalg.norm(P[fa] - P[fd], axis=-1) <= np.linalg.norm(P[fb] - P[fc], axis=-1)
    # Outward winding: (a, c, b) and (b, c, d) along diagonal b-c; (a, c, d), (a, d, b) along a-d.
    t1 = np.where(ad[:, None], np.stack([fa, fc, fd], -1), np.stack([fa, fc, fb], -1))
    t2 = np.where(ad[:, None], np.stack([fa, fd, fb], -1), np.stack([fb, fc, fd], -1))
    faces_px = np.concatenate([t1, t2]) if len(t1) else np.zeros((0, 3), dtype=np.int64)
    used = np.unique(faces_px)
    idx.ravel()[used] = np.arange(len(used))
    faces = idx.ravel()[faces_px]
    pixel = np.stack([used // W, used % W], axis=-1).astype(np.int64)
    return P[used].copy(), faces.astype(np.int64), pixel


def _check_mesh(vertices, faces):
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise ValueError(f"vertices: must be (N, 3), got shape {v.shape}")
    if not np.isfinite(v).all():
        raise ValueError("vertices: must be finite")
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"faces: must be (F, 3), got shape {f.shape}")
    if f.size and not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces: must be integers, got {f.dtype}")
    f = f.astype(np.int64)
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError(f"faces: indices must lie in [0, {len(v)}), found {f.min()}..{f.max()}")
    return v, f


def _unit(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    length = np.linalg.norm(x, axis=-1)
    ok = np.isfinite(length) & (length > 0)
    return np.where(ok[..., None], x / np.where(ok, length, 1.0)[..., None], 0.0), ok


def angular_error_deg(a, b) -> np.ndarray:
    """Angle [deg] between unit vectors `a` and `b` `(..., 3)`, via atan2 (accurate near 0)."""
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1)))


def face_averaged_normals(vertices, faces) -> np.ndarray:
    """`(N, 3)` unit area-weighted vertex normals (right-hand rule on each face's
    vertex order); `(0, 0, 0)` for a vertex in no non-degenerate face."""
    v, f = _check_mesh(vertices, faces)
    return _unit(area_normal_sums(v, f))[0]


def _frames(n: np.ndarray):
    """Two unit tangents `(N, 3)` completing each unit normal to a right-handed frame."""
    helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = _unit(np.cross(helper, n))[0]
    return t1, np.cross(n, t1)


_CHUNK = 8000  # vertices per block in the mesh fits (temporaries stay in cache)


def _mesh_fits(v, nbr, normal, weight_mask, centre_weight, gaussian=True, leverage=False):
    """Quadratic height field over each neighbourhood `nbr` `(n, k)` (first
    column: the vertex itself), in the frame of `normal` `(n, 3)` at the vertex.
    `weight_mask` `(n, k)` bool: samples used; `centre_weight` scales the
    vertex's own sample (0 = leave it out); `gaussian`: Gaussian weights
    (sigma = half the neighbourhood radius) rather than equal ones; `leverage`:
    also return the hat-matrix diagonal `(n, k)`.

    Coordinates are `xs, ys = (x, y) / rho` with `rho` the neighbourhood radius;
    heights stay in metres.

    **Returns:** dict with `c0..c5` `(n,)` coefficients, inverse normal matrix
    entries `_VAR_IDX` scaled so that `sigma2 * entry` is a covariance,
    `sigma2` `(n,)` weighted residual variance [m^2] (inf for an exact fit, NaN
    where no usable fit), `ok`, `rho` `(n,)` [m], frame `t1`, `t2`, `n`
    `(n, 3)`, `resid` `(n, k)` [m], `used` `(n, k)` bool (and `hat` `(n, k)`).
    """
    parts = [_mesh_fits_block(v, nbr[a:a + _CHUNK], normal[a:a + _CHUNK], weight_mask[a:a + _CHUNK],
                              centre_weight, gaussian, leverage)
             for a in range(0, len(nbr), _CHUNK)]
    return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}


def _mesh_fits_block(v, nbr, normal, weight_mask, centre_weight, gaussian, leverage):
    t1, t2 = _frames(normal)
    d = v[nbr] - v[nbr[:, :1]]  # (n, k, 3)
    x = np.einsum("nkj,nj->nk", d, t1)
    y = np.einsum("nkj,nj->nk", d, t2)
    z = np.einsum("nkj,nj->nk", d, normal)
    dist2 = x * x + y * y
    rho = np.sqrt(np.max(np.where(weight_mask, dist2, 0.0), axis=1))
    rho = np.where(rho > 0, rho, 1.0)
    xs, ys = x / rho[:, None], y / rho[:, None]
    if gaussian:
        w = np.exp(-2.0 * (xs * xs + ys * ys)) * weight_mask
    else:
        w = weight_mask.astype(np.float64)
    w[:, 0] *= centre_weight
    phi = _basis(xs, ys)  # (n, k, 6)
    wphi_t = phi.transpose(0, 2, 1) * w[:, None, :]
    M = np.matmul(wphi_t, phi)
    b = np.matmul(wphi_t, z[..., None])[..., 0]
    used = w > 0
    n_used = used.sum(1)
    Minv, ok = _solve_batched(M, n_used >= _NPARAM)
    coef = np.einsum("nij,nj->ni", Minv, b)
    c = [coef[:, i] for i in range(_NPARAM)]
    fit, _, _ = _evaluate([ci[:, None] for ci in c], xs, ys)
    resid = z - fit
    wsum = w.sum(1)
    # Weights normalised to mean 1 over the used samples: sigma2 is then a
    # per-sample variance and sigma2 * (sum wn phi phi^T)^-1 the covariance.
    wn = w * (n_used / np.where(wsum > 0, wsum, 1.0))[:, None]
    dof = n_used - _NPARAM
    sigma2 = np.where(dof > 0, np.sum(wn * resid**2, 1) / np.maximum(dof, 1), np.inf)
    scale = wsum / np.where(n_used > 0, n_used, 1)
    out = {f"c{i}": c[i] for i in range(_NPARAM)}
    out.update({ij: Minv[:, ij[0], ij[1]] * scale for ij in _VAR_IDX})
    out.update(sigma2=np.where(ok, sigma2, np.nan), ok=ok, rho=rho, t1=t1, t2=t2, n=normal,
               resid=resid, used=used)
    if leverage:
        # h_q = w_q phi_q^T Minv phi_q, phi = (1, x, y, x^2, xy, y^2).
        out["hat"] = w * np.einsum("nki,nij,nkj->nk", phi, Minv, phi, optimize=True)
        out["loo_var"] = Minv[:, 0, 0]  # variance factor of the fitted value at the vertex
    return out


def mesh_quadratic_normals(vertices, faces, k: int = 24, adaptive: bool = True,
                           outlier_k: float = 4.0, iterations: int = 2):
    """Denoised vertices and normals of a noisy mesh by local quadratic fits.

    For every vertex, its `k` nearest vertices (itself included; scipy cKDTree)
    are expressed in a local frame whose z axis is the vertex's normal (first the
    area-weighted face normals summed over the neighbourhood, then, for
    `iterations > 1`, the previous fit's normal); neighbours whose initial normal
    faces away (the other side of a thin part) are left out. A height field
    `h = quadratic(x, y)` is fitted by weighted least squares (Gaussian weights,
    sigma = half the neighbourhood radius).

    Outliers: each vertex is tested against a plain least-squares quadratic of
    its neighbours with itself left out. Its residual is compared with
    `outlier_k x scale x sqrt(1 + v0)`, where `v0` is the fit's variance factor
    at the vertex (prediction variance) and `scale` is robust: per vertex,
    1.4826 x the median of its neighbours' leverage-corrected residuals
    `|e| / sqrt(1 - h)`, then pooled as the median of that over the
    neighbourhood (a scale from ~20 residuals is noisy enough to give heavy
    tails), floored at 1e-3 x the neighbourhood radius. Vertices whose
    neighbourhood held a first-round outlier are tested again without them, so
    that a spike does not condemn its neighbours. Outliers are excluded from
    every fit and are moved onto a fit like any other vertex.

    Adaptive (discontinuity-aware) rule: with `adaptive=True` a vertex may take
    the fit of any of its `k` neighbours whose neighbourhood contains it, not only
    its own; the fit with the smallest estimated variance of the slope at the
    vertex (`max(sigma_hat^2, floor) g^T Cov g`, as `quadratic_fit`'s default
    `select`; `floor` = twice the median `sigma_hat^2` over all fits) wins, so
    fits straddling a crease or a gap lose to one-sided ones while on smooth
    ground the vertex's own, centred fit is kept.

    The vertex moves onto the chosen height field along that fit's frame normal;
    the normal is the height field's normal there, oriented like the initial
    normal. A vertex with no usable fit keeps its position and its initial
    normal.

    **Arguments:** `vertices` `(N, 3)` [m]; `faces` `(F, 3)` int; `k` >= 7 and
    <= N; `adaptive` bool; `outlier_k` > 0; `iterations` >= 1.

    **Returns:** `denoised_vertices` `(N, 3)` [m], `normals` `(N, 3)` unit,
    `outlier` `(N,)` bool.
    """
    v, f = _check_mesh(vertices, faces)
    if not _is_int(k, 7):
        raise ValueError(f"k: must be an integer >= 7, got {k!r}")
    if k > len(v):
        raise ValueError(f"k: must not exceed the number of vertices ({len(v)}), got {k}")
    outlier_k = _check_positive("outlier_k", outlier_k)
    if not _is_int(iterations, 1):
        raise ValueError(f"iterations: must be an integer >= 1, got {iterations!r}")
    N, k = len(v), int(k)

    area = area_normal_sums(v, f)
    _, nbr = cKDTree(v).query(v, k=k)
    nbr = np.asarray(nbr, dtype=np.int64)
    # Make sure each vertex is first in its own list (ties with duplicates).
    self_pos = np.argmax(nbr == np.arange(N)[:, None], axis=1)
    has_self = (nbr == np.arange(N)[:, None]).any(1)
    nbr[has_self, self_pos[has_self]] = nbr[has_self, 0]
    nbr[:, 0] = np.arange(N)
    # Initial normal: the area-weighted face normals summed over the neighbourhood.
    # A vertex's own face normal is as noisy as the data (tens of degrees at a
    # noise near the sampling step, sometimes past 90): too noisy to orient by.
    n0, has0 = _unit(area[nbr].sum(1))
    n0[~has0] = _unit(area)[0][~has0]
    n0[np.linalg.norm(n0, axis=1) == 0] = [0.0, 1.0, 0.0]
    same_side = np.einsum("nkj,nj->nk", n0[nbr], n0) > 0
    same_side[:, 0] = True

    def outlier_round(rows, mask):
        # Plain least squares over the neighbours with the vertex left out: the
        # vertex's residual, the fit's prediction-variance factor there, and a
        # robust scale from the neighbours' leverage-corrected residuals.
        fit = _mesh_fits(v, nbr[rows], n0[rows], same_side[rows] & mask, centre_weight=0.0,
                         gaussian=False, leverage=True)
        std = np.abs(fit["resid"]) / np.sqrt(np.clip(1.0 - fit["hat"], 0.05, 1.0))
        std = np.where(fit["used"], std, np.nan)
        std[:, 0] = np.nan
        none = np.isnan(std).all(1, keepdims=True)
        raw = _MAD * np.nanmedian(np.where(none, 0.0, std), axis=1)
        return np.abs(fit["resid"][:, 0]), raw, fit["loo_var"], fit["ok"], fit["rho"]

    def decide(rows, res, raw_all, loo, ok, rho):
        # A scale from ~20 residuals is itself noisy (heavy-tailed ratios), so
        # pool it: the median of the neighbours' scales.
        scale = np.maximum(np.median(raw_all[nbr[rows]], axis=1), 1e-3 * rho)
        return ok & (res > outlier_k * scale * np.sqrt(1.0 + loo))

    all_rows = np.arange(N)
    res, raw, loo, ok, rho = outlier_round(all_rows, np.ones((N, k), dtype=bool))
    first = decide(all_rows, res, raw, loo, ok, rho)
    # Second round, only where a neighbour was flagged: re-test without the flagged.
    touched = np.flatnonzero(first[nbr[:, 1:]].any(1))
    outlier = first.copy()
    if len(touched):
        res2, raw2, loo2, ok2, rho2 = outlier_round(touched, ~first[nbr[touched]])
        raw[touched] = raw2
        outlier[touched] = decide(touched, res2, raw, loo2, ok2, rho2)
    keep = ~outlier[nbr]

    normal = n0
    for _ in range(iterations):
        fit = _mesh_fits(v, nbr, normal, same_side & keep, centre_weight=1.0)
        normal_new, pts = _evaluate_mesh_fits(v, nbr, fit, n0, adaptive)
        normal = np.where(np.isfinite(normal_new).all(1, keepdims=True), normal_new, normal)
        good = np.isfinite(pts).all(1)
    denoised = np.where(good[:, None], pts, v)
    normal, ok = _unit(np.where(good[:, None], normal, n0))
    normal[~ok] = n0[~ok]
    return denoised, normal, outlier


def _evaluate_mesh_fits(v, nbr, fit, n_orient, adaptive):
    """Pick, for every vertex, the best fit among its candidates and evaluate it
    there: `(normals (N, 3), points (N, 3))`, NaN where no fit is usable."""
    N, k = nbr.shape
    # contains[i, m]: is vertex i among the k nearest of its m-th neighbour c,
    # i.e. no farther from c than c's k-th nearest? (kNN is not symmetric.)
    dist = np.linalg.norm(v[nbr] - v[:, None, :], axis=-1)
    contains = dist <= dist.max(axis=1)[nbr] * (1 + 1e-12)
    names = [f"c{i}" for i in range(_NPARAM)] + list(_VAR_IDX) + ["sigma2", "rho"]
    table = np.concatenate([np.stack([fit[key] for key in names], 1),
                            fit["t1"], fit["t2"], fit["n"]], 1)
    floor = _noise_floor(fit["sigma2"])
    normals = np.full((N, 3), np.nan)
    points = np.full((N, 3), np.nan)
    for a in range(0, N, _CHUNK):
        blk = slice(a, min(a + _CHUNK, N))
        normals[blk], points[blk] = _evaluate_block(
            v, v[blk], nbr[blk], contains[blk], table, names, n_orient[blk], floor,
            k if adaptive else 1)
    return normals, points


def _evaluate_block(v, vb, nbr, contains, table, names, n_orient, floor, n_cand):
    n = len(vb)
    best_key = np.full(n, np.inf)
    best_n = np.full((n, 3), np.nan)
    best_p = np.full((n, 3), np.nan)
    for m in range(n_cand):
        c = nbr[:, m]
        row = table[c]
        f = {key: row[:, i] for i, key in enumerate(names)}
        rho = f["rho"]
        t1, t2, nc = row[:, -9:-6], row[:, -6:-3], row[:, -3:]
        d = vb - v[c]
        xs = np.einsum("nj,nj->n", d, t1) / rho
        ys = np.einsum("nj,nj->n", d, t2) / rho
        hgt, hx, hy = _evaluate([f[f"c{i}"] for i in range(_NPARAM)], xs, ys)
        hx, hy = hx / rho, hy / rho
        vs, vt = _slope_variances(f, xs, ys)
        sig2 = f["sigma2"]
        key = np.where(np.isinf(sig2), _BIG, np.maximum(sig2, floor) * (vs + vt) / rho**2)
        key = np.where(contains[:, m] & np.isfinite(key), key, np.inf)
        nrm, okn = _unit(nc - hx[:, None] * t1 - hy[:, None] * t2)
        better = (key < best_key) & okn
        if not better.any():
            continue
        best_key[better] = key[better]
        flip = np.where(np.einsum("nj,nj->n", nrm, n_orient) < 0, -1.0, 1.0)
        best_n[better] = nrm[better] * flip[better, None]
        best_p[better] = (v[c] + (xs * rho)[:, None] * t1 + (ys * rho)[:, None] * t2
                          + hgt[:, None] * nc)[better]
    return best_n, best_p
