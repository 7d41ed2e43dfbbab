"""Estimation results: the `RESULT.npz` file and errors against ground truth.

Format version 1 (`N` points):

| key | shape, dtype | meaning |
|---|---|---|
| `format_version` | scalar int | 1 |
| `pd` | (N, 3) float | diffuse albedo |
| `ps` | (N,) float | specular reflectance |
| `sigma` or `alpha` | (N,) float | roughness [rad]: Torrance-Sparrow sigma or Ward alpha |
| `status` | (N,) int8 | 0 measured, 1 interpolated, 2 unresolved, 3 pooled |
| `std_pd`, `std_ps`, `std_rough` | (N, 3), (N,), (N,) float | standard deviations; inf = unknown |
| `specular_identifiable`, `pd_measured` | (N,) bool | which parameters came from the point's own samples |
| `meta` | 0-d str | JSON: method, model, options, seconds per stage, versions |
| `material` (optional) | (N,) int | the shared prior's material of each point |
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np
from jaxtyping import Bool, Float, Int

from .scan.io import ScanError, atomic_write
from .status import STATUS_NAMES, Status

__all__ = ["Estimate", "ROUGHNESS_NAME", "RESULT_VERSION", "ResultError", "save_result", "load_result", "check_estimate", "truth_errors"]

RESULT_VERSION = 1
ROUGHNESS_NAME = {"torrance-sparrow": "sigma", "ward": "alpha"}  # the roughness key per model


@dataclass(frozen=True)
class Estimate:
    """Per-point reflectance: `pd` `(N, 3)`, `ps` `(N,)`, `roughness` `(N,)`
    [rad] (sigma or alpha, per `model`), `status` `(N,)` int8 (`Status` codes), standard
    deviations `std_pd` `(N, 3)`, `std_ps`, `std_roughness` `(N,)`,
    `specular_identifiable` `(N,)` bool (ps and roughness from the point's own
    samples), `pd_measured` `(N,)` bool (the point had usable samples), and
    `meta` (options, timings), and `material` `(N,)` int (the shared prior's material of
    each point; None where no prior was fitted)."""

    pd: Float[np.ndarray, "N 3"]
    ps: Float[np.ndarray, " N"]
    roughness: Float[np.ndarray, " N"]
    status: Int[np.ndarray, " N"]
    std_pd: Float[np.ndarray, "N 3"]
    std_ps: Float[np.ndarray, " N"]
    std_roughness: Float[np.ndarray, " N"]
    specular_identifiable: Bool[np.ndarray, " N"]
    pd_measured: Bool[np.ndarray, " N"]
    model: str
    meta: dict = field(default_factory=dict)
    material: Int[np.ndarray, " N"] | None = None

    # Conveniences, each delegating to the module that owns the work (imported late: those
    # modules import this one).
    @property
    def seconds(self) -> dict:
        """Seconds per stage (`meta['seconds']`, e.g. `classify`, `fit`, `fill`)."""
        return dict(self.meta.get("seconds", {}))

    def status_counts(self) -> dict:
        """Points per `Status`: `{Status.MEASURED: n, ...}` (every member, 0 where none)."""
        return {s: int(np.count_nonzero(self.status == s)) for s in Status}

    def save(self, path) -> None:
        """Write a result file atomically (`jaxrefl.result.save_result`; `load_result` reads it)."""
        save_result(path, self)

    def relight(self, scan, light_pos: Float[np.ndarray, " 3"], intensity: float | None = None,
                **kw) -> Float[np.ndarray, "H W 3"]:
        """Linear image `(H, W, 3)` [W/(sr m^2)] of the object under a point light at
        `light_pos` `(3,)` [m] (`jaxrefl.outputs.relight.relight_image`: `camera`, `model_gi`,
        `width`, `height`); NaN off the object."""
        from .outputs.relight import relight_image

        return relight_image(self, scan, light_pos, intensity, **kw)

    def to_ply(self, path, scan) -> None:
        """Binary PLY of `scan`'s mesh with this result per vertex (`jaxrefl.outputs.export`)."""
        from .outputs.export import export_ply

        export_ply(path, scan.vertices, scan.faces, scan.normals, self)

    def figure(self, scan=None, **kw):
        """A matplotlib `Figure` (nothing written): the reflectance and status maps over
        `scan`'s geometry, or without a scan histograms of pd, ps, roughness and the
        status counts (`jaxrefl.outputs.render.estimate_figure`)."""
        from .outputs.render import estimate_figure

        return estimate_figure(self, scan, **kw)


class ResultError(ScanError):
    """A result file or `Estimate` failed validation; `field` names the key, `path` the file
    (None for an in-memory estimate). A `ScanError`, hence a `ValueError`."""

    def __init__(self, path, field_name: str, message: str):
        ValueError.__init__(self, f"{path}: {field_name}: {message}" if path is not None
                            else f"{field_name}: {message}")
        self.field, self.path = field_name, path


def check_estimate(est: Estimate, path=None) -> Estimate:
    """Check the shapes, dtypes and values of every field of `est` (`N` points: `pd` `(N, 3)`,
    `ps`, `roughness` `(N,)` finite; standard deviations never NaN, inf = unknown; `status` in
    0..3; the masks bool); return it with NumPy arrays or raise `ResultError` naming the key
    as the result file calls it (`path`: the file, for the message)."""
    if est.model not in ROUGHNESS_NAME:
        raise ResultError(path, "meta", f"unknown model {est.model!r}, expected one of {sorted(ROUGHNESS_NAME)}")
    rough = ROUGHNESS_NAME[est.model]
    pd = np.asarray(est.pd)
    if pd.ndim != 2 or pd.shape[1] != 3:
        raise ResultError(path, "pd", f"must have shape (N, 3), got {pd.shape}")
    n = len(pd)
    out = {}
    for attr, key, shape, kind, finite in (
        ("pd", "pd", (n, 3), "fiu", True), ("ps", "ps", (n,), "fiu", True), ("roughness", rough, (n,), "fiu", True),
        ("std_pd", "std_pd", (n, 3), "fiu", False), ("std_ps", "std_ps", (n,), "fiu", False),
        ("std_roughness", "std_rough", (n,), "fiu", False), ("status", "status", (n,), "iu", True),
        ("specular_identifiable", "specular_identifiable", (n,), "b", True),
        ("pd_measured", "pd_measured", (n,), "b", True), ("material", "material", (n,), "iu", True),
    ):
        value = getattr(est, attr)
        if value is None and attr == "material":
            out[attr] = None
            continue
        arr = np.asarray(value)
        if arr.dtype.kind not in kind:
            want = {"fiu": "a float", "iu": "an integer", "b": "a bool"}[kind]
            raise ResultError(path, key, f"must be {want} array, got dtype {arr.dtype}")
        if arr.shape != shape:
            raise ResultError(path, key, f"must have shape {shape} (N = {n} points, from pd), got {arr.shape}")
        bad = ~np.isfinite(arr) if finite else np.isnan(arr)
        if kind == "fiu" and np.any(bad):
            what = "non-finite value(s) (NaN or inf)" if finite else "NaN value(s) (inf marks an unknown std)"
            raise ResultError(path, key, f"contains {int(bad.sum())} {what}, first at point "
                                         f"{int(np.argmax(bad.reshape(n, -1).any(axis=1)))}")
        out[attr] = arr
    status = out["status"]
    if n and (status.min() < 0 or status.max() >= len(STATUS_NAMES)):
        raise ResultError(path, "status", f"codes must lie in [0, {len(STATUS_NAMES) - 1}], "
                                          f"found [{status.min()}, {status.max()}]")
    return Estimate(**out, model=est.model, meta=est.meta)


def save_result(path, est: Estimate) -> None:
    """Check `est` (`check_estimate`: `ResultError` naming the field, nothing written) and
    write it to `path` atomically."""
    from ._version import __version__

    est = check_estimate(est)
    meta = dict(est.meta, jaxrefl_version=__version__)
    arrays = {
        "format_version": np.int64(RESULT_VERSION),
        "pd": est.pd, "ps": est.ps, ROUGHNESS_NAME[est.model]: est.roughness,
        "status": est.status.astype(np.int8), "std_pd": est.std_pd, "std_ps": est.std_ps,
        "std_rough": est.std_roughness, "specular_identifiable": est.specular_identifiable,
        "pd_measured": est.pd_measured, "meta": np.asarray(json.dumps(meta, sort_keys=True)),
    }
    if est.material is not None:
        arrays["material"] = np.asarray(est.material, np.int32)
    atomic_write(path, lambda fh: np.savez(fh, **arrays))


_REQUIRED = ("pd", "ps", "status", "std_pd", "std_ps", "std_rough", "specular_identifiable", "pd_measured")


def load_result(path) -> Estimate:
    """Read and check a result file written by `save_result`; raises `ResultError` (a
    `ScanError`, hence `ValueError`) naming the file and the bad key."""
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise
    except Exception as exc:  # zipfile / pickle / format errors, truncated files
        raise ResultError(path, "file", f"not a readable .npz result file ({type(exc).__name__}: {exc})") from None
    if "format_version" not in data:
        raise ResultError(path, "format_version", "missing: not a jaxrefl result file")
    version = data["format_version"]
    if version.shape != () or version.dtype.kind not in "iu" or int(version) != RESULT_VERSION:
        raise ResultError(path, "format_version", f"unsupported version {version!r}, this jaxrefl reads "
                                                  f"{RESULT_VERSION}")
    if "pd" not in data and "vertices" in data:
        raise ResultError(path, "pd", "missing: this is a scan bundle, not a result file (jaxrefl estimate "
                                      "writes one)")
    if "meta" not in data:
        raise ResultError(path, "meta", "missing")
    try:
        meta = json.loads(str(data["meta"]))
    except json.JSONDecodeError as exc:
        raise ResultError(path, "meta", f"not valid JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise ResultError(path, "meta", f"must be a JSON object, got {type(meta).__name__}")
    model = meta.get("model")
    if model not in ROUGHNESS_NAME:
        raise ResultError(path, "meta", f"unknown model {model!r}, expected one of {sorted(ROUGHNESS_NAME)}")
    for key in (*_REQUIRED, ROUGHNESS_NAME[model]):
        if key not in data:
            raise ResultError(path, key, "missing")
    est = Estimate(data["pd"], data["ps"], data[ROUGHNESS_NAME[model]], data["status"], data["std_pd"],
                   data["std_ps"], data["std_rough"], data["specular_identifiable"], data["pd_measured"], model,
                   meta, data.get("material"))
    return check_estimate(est, path)


def _rel(a, b):
    return np.abs(a - b) / np.maximum(np.abs(b), 1e-12)


def truth_errors(est: Estimate, scan) -> dict:
    """Median and 90th-percentile relative errors of pd, ps and roughness against the
    scan's ground truth, over measured points and over all points (absolute errors
    where the truth is 0). Roughness is
    compared only when the truth is in the estimate's model (sigma vs alpha)."""
    measured = est.status == 0
    truth_rough = scan.true_sigma if est.model == "torrance-sparrow" else scan.true_alpha
    out = {}
    for name, value, truth in (("pd", est.pd, scan.true_pd), ("ps", est.ps, scan.true_ps),
                               ("roughness", est.roughness, truth_rough)):
        if truth is None:
            continue
        err = _rel(value, truth)
        err = err.reshape(len(err), -1).mean(axis=1)
        # Relative error is undefined where the truth is 0 (e.g. ps of a matte surface):
        # those points are summarised by their absolute error instead.
        zero = np.abs(truth).reshape(len(err), -1).max(axis=1) <= 1e-9
        absolute = np.abs(value - truth).reshape(len(err), -1).mean(axis=1)
        entry = {}
        for label, mask in (("measured", measured), ("all", np.ones_like(measured))):
            if (mask & ~zero).any():
                entry[label] = {"median": float(np.median(err[mask & ~zero])),
                                "p90": float(np.percentile(err[mask & ~zero], 90))}
            if (mask & zero).any():
                entry[label + "_where_truth_is_0"] = {"median_abs": float(np.median(absolute[mask & zero])),
                                                      "p90_abs": float(np.percentile(absolute[mask & zero], 90))}
        out[name] = entry
    return out
