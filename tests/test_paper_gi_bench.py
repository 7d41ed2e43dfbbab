"""benchmarks.paper_gi: the cached path-traced scan and the errors it reports (a tiny mesh, few
paths; no Method III run)."""

import dataclasses
import math

import numpy as np

from benchmarks import paper_gi
from jaxrefl.outputs.relight import truth_estimate
from jaxrefl.status import Status


def test_the_scan_is_rendered_once_then_loaded(tmp_path, monkeypatch):
    monkeypatch.setenv("JAXREFL_ZOO_CACHE", str(tmp_path))
    scan, _, cached = paper_gi.gi_scan(16, 4)
    assert not cached and (tmp_path / "paper_E_16_4.npz").exists()
    again, _, cached = paper_gi.gi_scan(16, 4)
    assert cached
    np.testing.assert_array_equal(again.radiance, scan.radiance)
    np.testing.assert_array_equal(again.true_pd, scan.true_pd)
    assert scan.n_lights == len(paper_gi.PAPER_LIGHTS)


def test_errors_are_zero_at_the_truth_and_follow_a_known_offset(tmp_path, monkeypatch):
    monkeypatch.setenv("JAXREFL_ZOO_CACHE", str(tmp_path))
    scan, _, _ = paper_gi.gi_scan(16, 4)
    truth = truth_estimate(scan)
    e = paper_gi.errors(truth, scan, 16)
    for key in ("pd_all", "pd_observed", "pd_far", "ps_observed", "alpha_observed"):
        assert e[key] < 1e-6, (key, e[key])
    off = dataclasses.replace(truth, pd=truth.pd * 1.1, ps=truth.ps * 0.8, roughness=truth.roughness * 1.5,
                              status=np.full(scan.n_points, Status.UNRESOLVED, np.int8))
    e = paper_gi.errors(off, scan, 16)
    assert math.isclose(e["pd_all"], 0.1, rel_tol=1e-6) and math.isclose(e["pd_far"], 0.1, rel_tol=1e-6)
    assert math.isclose(e["ps_observed"], 0.2, rel_tol=1e-6) and math.isclose(e["alpha_observed"], 0.5, rel_tol=1e-6)
    assert e["measured_or_pooled"] == 0.0
