"""benchmarks/calibration.py's measures on made-up estimates with known |error| / sd."""

from types import SimpleNamespace

import numpy as np
import pytest

from benchmarks import calibration
from jaxrefl.status import Status


def _case():
    n = 8
    truth = SimpleNamespace(true_pd=np.full((n, 3), 0.5), true_ps=np.full(n, 0.2), true_alpha=np.full(n, 0.1))
    observed = np.ones((n, 4), bool)
    observed[7] = False  # never observed: left out
    truth.observed = lambda: observed
    k = np.array([0.5, 0.5, 2.0, 4.0, 0.0, 5.0, 0.9, 9.0])  # |error| in sd
    std = np.full(n, 0.01)
    est = SimpleNamespace(
        pd=truth.true_pd + (k * std)[:, None], std_pd=np.repeat(std[:, None], 3, 1),
        ps=truth.true_ps - k * std, std_ps=np.where(np.arange(n) == 4, np.inf, std),
        roughness=truth.true_alpha * np.exp(k * 0.1), std_roughness=truth.true_alpha * np.exp(k * 0.1) * 0.1,
        status=np.array([Status.MEASURED] * 4 + [Status.UNRESOLVED] + [Status.POOLED] * 3))
    return est, truth, k


def test_z_scores_are_error_over_sd_and_nan_without_a_finite_sd():
    est, truth, k = _case()
    z = calibration.z_scores(est, truth)
    np.testing.assert_allclose(z["pd"], np.repeat(k[:, None], 3, 1), rtol=1e-9)
    np.testing.assert_allclose(np.delete(z["ps"][:, 0], 4), np.delete(k, 4), rtol=1e-9)
    assert np.isnan(z["ps"][4, 0])  # sd inf: no statement to check
    np.testing.assert_allclose(z["roughness"][:, 0], k, rtol=1e-9)  # in ln roughness


def test_shares_per_status_over_observed_points():
    est, truth, _ = _case()
    cal = calibration.calibration(est, truth)
    ps = cal["ps"]
    # observed with finite sd: rows 0-3, 5, 6 (4 has sd inf, 7 is not observed): |error| 0.5 0.5 2 4 5 0.9
    assert ps["all"]["n"] == 6
    assert ps["all"]["beyond_3"] == pytest.approx(2 / 6) and ps["all"]["within_1"] == pytest.approx(3 / 6)
    assert ps["all"]["median"] == pytest.approx(1.45)
    assert ps["measured"]["n"] == 4 and ps["measured"]["beyond_3"] == pytest.approx(1 / 4)
    assert ps["pooled"]["n"] == 2 and "interpolated" not in ps
    assert cal["pd"]["all"]["n"] == 7 * 3  # every channel of every observed point
    rows = calibration.table([{"object": "B", "method": "local", "observed": 7, "calibration": cal}])
    assert rows[2].startswith("| B | local | 7 | pd |") and "33.3 % / 50 % (z 1.45)" in rows[3]
