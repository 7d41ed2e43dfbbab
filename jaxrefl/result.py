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

import numpy as np

from .io import atomic_write
from .local import ROUGHNESS_NAME, Estimate

__all__ = ["RESULT_VERSION", "save_result", "load_result", "truth_errors"]

RESULT_VERSION = 1


def save_result(path, est: Estimate) -> None:
    """Write `est` to `path` atomically."""
    from . import __version__

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


def load_result(path) -> Estimate:
    """Read a result file written by `save_result` (raises ValueError naming a bad field)."""
    with np.load(path, allow_pickle=False) as z:
        data = {k: z[k] for k in z.files}
    if int(data.get("format_version", -1)) != RESULT_VERSION:
        raise ValueError(f"format_version: not a version-{RESULT_VERSION} jaxrefl result")
    meta = json.loads(str(data["meta"]))
    model = meta.get("model")
    if model not in ROUGHNESS_NAME:
        raise ValueError(f"meta: unknown model {model!r}")
    rough = data[ROUGHNESS_NAME[model]]
    return Estimate(data["pd"], data["ps"], rough, data["status"], data["std_pd"], data["std_ps"],
                    data["std_rough"], data["specular_identifiable"], data["pd_measured"], model, meta,
                    data.get("material"))


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
