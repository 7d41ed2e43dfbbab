"""benchmarks/scaling.py on synthetic numbers: the exponent fit, the skip rule, the grid driver,
the table writer and the plot. The benchmark itself (minutes) is never run here."""

import json
import math
import os

import numpy as np
import pytest

from benchmarks import scaling

GIB = scaling.GIB
MIB = 2**20


def _cell(x, first, warm, peak, imports=300 * MIB, loaded=None, cold=False):
    loaded = imports + 10 * MIB if loaded is None else loaded
    return {"x": x, "first": first, "warm": warm, "peak_rss": peak, "rss_imports": imports, "rss_loaded": loaded,
            "cold": cold}


def test_fit_exponent_recovers_power_laws():
    x = np.array([1e4, 3e4, 1e5, 3e5, 1e6])
    for p in (0.5, 1.0, 1.3, 2.0):
        slope, intercept = scaling.fit_exponent(x, 7.0 * x**p)
        assert slope == pytest.approx(p, abs=1e-9)
        assert math.exp(intercept) == pytest.approx(7.0, rel=1e-9)
    # n log n: the local slope is a little above 1 and falls slowly
    slope, _ = scaling.fit_exponent(x, x * np.log(x))
    assert 1.05 < slope < 1.15
    # a fixed cost flattens the fit over all sizes but not between the largest two
    y = 3.0 + 1e-4 * x
    assert scaling.fit_exponent(x, y)[0] < 0.8
    assert scaling.fit_exponent(x[-2:], y[-2:])[0] > 0.9
    # unusable input: NaN, not an exception
    assert math.isnan(scaling.fit_exponent([1e4], [2.0])[0])
    assert math.isnan(scaling.fit_exponent([1e4, 1e4], [2.0, 3.0])[0])
    assert scaling.fit_exponent([1e4, 2e4, 4e4], [1.0, 0.0, 4.0])[0] == pytest.approx(1.0)  # zero left out


def test_predict_scales_the_warm_time_with_a_slope_never_below_one():
    # one cell: linear; compile (first - warm) held
    pred = scaling.predict([_cell(1e4, 12.0, 2.0, 1 * GIB)], 3e4, cold=False)
    assert pred["p"] == 1.0
    assert pred["warm"] == pytest.approx(6.0)
    assert pred["seconds"] == pytest.approx(10.0 + 2 * 6.0)
    # two cells, quadratic warm time: slope 2 is used
    h = [_cell(1e4, 11.0, 1.0, 1 * GIB), _cell(2e4, 14.0, 4.0, 1 * GIB)]
    pred = scaling.predict(h, 4e4, cold=False)
    assert pred["p"] == pytest.approx(2.0)
    assert pred["warm"] == pytest.approx(16.0)
    # sub-linear measured growth (fixed costs) is not trusted: slope 1
    h = [_cell(1e4, 11.0, 4.0, 1 * GIB), _cell(2e4, 12.0, 5.0, 1 * GIB)]
    assert scaling.predict(h, 4e4, cold=False)["p"] == 1.0
    # no history: no prediction
    assert scaling.predict([], 1e5) is None


def test_predict_compile_share_of_a_cold_cell():
    cold = _cell(1e4, 52.0, 2.0, 1 * GIB, cold=True)
    # the next cell loads programs from the cache: a share of the cold compile time
    pred = scaling.predict([cold], 1e4, cold=False)
    assert pred["first"] - pred["warm"] == pytest.approx(50.0 * scaling.CACHED_SHARE)
    # once a cached cell is measured, its own extra seconds are used
    pred = scaling.predict([cold, _cell(2e4, 9.0, 4.0, 1 * GIB)], 4e4, cold=False)
    assert pred["first"] - pred["warm"] == pytest.approx(5.0)
    # every cell cold: the cold compile time
    assert scaling.predict([cold], 2e4, cold=True)["first"] == pytest.approx(50.0 + 4.0)


def test_predict_memory_baseline_scan_and_work():
    imports, loaded = 400 * MIB, 500 * MIB
    h = [_cell(1e4, 5, 1, 700 * MIB, imports, loaded)]  # work 200 MiB, scan 100 MiB
    pred = scaling.predict(h, 1e5, cold=False)
    assert pred["peak_rss"] == pytest.approx(imports + 100 * MIB * 10 + 200 * MIB * 10)
    # work memory growing quadratically is extrapolated quadratically
    h = [_cell(1e4, 5, 1, loaded + 100 * MIB, imports, loaded), _cell(2e4, 6, 2, loaded + 400 * MIB, imports, loaded)]
    pred = scaling.predict(h, 4e4, cold=False)
    assert pred["q"] == pytest.approx(2.0)
    assert pred["peak_rss"] == pytest.approx(imports + 100 * MIB * 2 + 400 * MIB * 4)


def test_skip_reason_budget_and_memory():
    h = [_cell(1e5, 20.0, 10.0, 1 * GIB)]
    # the budget bounds the first call: compile 10 s + warm 100 s at 1M runs, 10 + 200 s at 2M does not
    assert scaling.skip_reason(h, 1e6, budget=120, mem_limit=16 * GIB, cold=False) is None
    why = scaling.skip_reason(h, 2e6, budget=120, mem_limit=16 * GIB, cold=False)
    assert why == "skipped: predicted 210 s (first call) > 120 s budget"
    why = scaling.skip_reason(h, 1e6, budget=1000, mem_limit=4 * GIB, cold=False)
    assert "GiB memory limit" in why and why.startswith("skipped: predicted")
    assert scaling.skip_reason([], 1e6, budget=1, mem_limit=1) is None  # nothing to extrapolate: run


def _fake_measure(cost, calls):
    """A `measure` whose warm seconds are `cost(method, n, m)`; compile 30 s cold, 3 s cached."""
    def measure(method, n, m, cold):
        calls.append((method, n, m, cold))
        warm = cost(method, n, m)
        if warm is None:
            return {"error": "failed (exit 1): boom", "peak_rss": 500 * MIB}
        return {"first": warm + (30.0 if cold else 3.0), "warm": warm, "peak_rss": int(400 * MIB + n * 2e3),
                "rss_imports": 300 * MIB, "rss_loaded": int(300 * MIB + n * 200), "points": n + 1, "lights": m,
                "stages_warm": {"classify": 0.1 * warm, "fit": 0.9 * warm},
                "substages_warm": {"checks": {"calls": 1, "seconds": 0.01 * warm}},
                "stages_first": {}, "substages_first": {}}
    return measure


def test_run_grid_skips_extrapolated_cells_and_shares_the_common_cell():
    todo = scaling.grid(False, ("local", "radiosity"))
    assert ("lights", "local", scaling.FIXED_POINTS, scaling.FIXED_LIGHTS) in todo
    calls = []
    quadratic = lambda method, n, m: (n / 1e4) ** (1 if method == "local" else 2) * m / 12  # noqa: E731
    cells = scaling.run_grid(todo, _fake_measure(quadratic, calls), budget=120, mem_limit=16 * GIB,
                             log=lambda *_: None)
    assert len(cells) == len(todo)
    by = {(c["sweep"], c["method"], c["points"] if "error" in c else c["points"] - 1, c["lights"]): c for c in cells}
    # Method I, linear: every size runs (first call at 1M: 3 + 100 s)
    assert all("error" not in by[("points", "local", n, 12)] for n in scaling.POINTS)
    # Method II, quadratic: up to 100k (first call 3 + 100 s); 300k predicted 3 + 900 s: skipped, and so is
    # every larger size without a prediction of its own
    assert "error" not in by[("points", "radiosity", 100_000, 12)]
    assert "budget" in by[("points", "radiosity", 300_000, 12)]["error"]
    assert by[("points", "radiosity", 1_000_000, 12)]["error"] == "skipped: a smaller size was skipped or failed"
    # the common cell (30k points, 12 lights) is measured once and appears in both sweeps
    assert sum(1 for c in calls if c[:3] == ("local", scaling.FIXED_POINTS, scaling.FIXED_LIGHTS)) == 1
    shared = by[("lights", "local", scaling.FIXED_POINTS, scaling.FIXED_LIGHTS)]
    assert shared["note"] == "same cell as the other sweep"
    # only each method's first cell compiles cold
    assert [c[3] for c in calls if c[0] == "local"][:2] == [True, False]
    assert sum(c[3] for c in calls) == 2


def test_run_grid_failure_and_total_budget():
    calls = []
    todo = [("points", "local", n, 12) for n in (10_000, 30_000, 100_000)]
    cells = scaling.run_grid(todo, _fake_measure(lambda *_: None, calls), 120, 16 * GIB, log=lambda *_: None)
    assert cells[0]["error"].startswith("failed")
    assert cells[1]["error"] == cells[2]["error"] == "skipped: a smaller size was skipped or failed"
    assert len(calls) == 1
    t = iter([0.0, 0.0, 1000.0, 1000.0, 1000.0])
    cells = scaling.run_grid(todo, _fake_measure(lambda *_: 1.0, []), 120, 16 * GIB, total_budget=500,
                             clock=lambda: next(t), log=lambda *_: None)
    assert "error" not in cells[0]
    assert cells[1]["error"] == "skipped: the run's 500 s were spent"


def _settings(**extra):
    return {"date": "2026-01-01T00:00:00", "cores": 2, "platform": "linux", "python": "3.11", "jax": "0.10",
            "backend": "cpu", "x64": False, "command": "python3 -m benchmarks.scaling", "wall": 100.0,
            "build_seconds": 10.0, "load": [1.0, 2.0], "photon": dict(scaling.PHOTON), "budget": 120.0,
            "max_gib": 16.0, "mem_limit": 12 * GIB, "fixed_lights": 12, "fixed_points": 30_000,
            "compile_cache": "shared", "methods": ["local", "radiosity"], **extra}


def test_tables_markdown_json_and_plot(tmp_path):
    calls = []
    cost = lambda method, n, m: 1e-4 * n * (m / 12) * (1 if method == "local" else 3)  # noqa: E731
    todo = scaling.grid(False, ("local", "radiosity"))
    cells = scaling.run_grid(todo, _fake_measure(cost, calls), 120, 16 * GIB, log=lambda *_: None)
    rows = scaling.table(cells, "points")
    assert rows[0].startswith("| method | points | lights | first [s] | warm [s] | peak RSS [MiB]")
    assert len(rows) == 2 + sum(c["sweep"] == "points" for c in cells)
    assert any("skipped: predicted" in r for r in rows)
    assert any("cold compile" in r for r in rows)
    row = next(r for r in rows if r.startswith("| Method I") and "| 30,001 |" in r)
    cols = [c.strip() for c in row.strip("|").split("|")]
    assert cols[3:6] == ["6.00", "3.00", f"{(400 * MIB + 30_000 * 2e3) / MIB:,.0f}"]
    assert cols[7] == "10,000"  # points / warm second

    ex = scaling.exponents(cells, ("local", "radiosity"))
    # warm time is exactly linear in points, and in lights, for the synthetic cost
    assert ex["local/points"]["warm"] == pytest.approx(1.0, abs=1e-3)
    assert ex["radiosity/lights"]["warm_last"] == pytest.approx(1.0, abs=1e-6)
    growth = scaling.stage_growth(cells, "local", "points")
    assert {r[0] for r in growth} == {"classify", "fit", "sub: checks"}
    assert all(r[3] == pytest.approx(1.0, abs=1e-3) for r in growth)

    md = tmp_path / "RESULTS_scaling.md"
    md.write_text("old\n" + scaling.FINDINGS_MARK + "\nhand-written findings\n")
    text = scaling.write_markdown(str(md), cells, _settings(), ("local", "radiosity"))
    assert "## Fitted exponents" in text and "| Method I (Local(), prior) | 1.00" in text
    kept = md.read_text()
    assert kept.count(scaling.FINDINGS_MARK) == 1 and kept.rstrip().endswith("hand-written findings")
    assert "old\n" not in kept
    json.dumps({"cells": cells, "exponents": ex}, default=float)  # JSON-able
    png = tmp_path / "scaling.png"
    scaling.plot(str(png), cells, ("local", "radiosity"))
    assert png.stat().st_size > 10_000


def test_flatten_seconds_and_method_specs():
    flat = scaling.flatten_seconds({"classify": 1, "local_stages": {"fit": 2.0, "deeper": {"x": 3}}, "name": "s"})
    assert flat == {"classify": 1.0, "local_stages/fit": 2.0, "local_stages/deeper/x": 3.0}
    import jaxrefl

    assert isinstance(scaling.method_spec("local"), jaxrefl.Local)
    photon = scaling.method_spec("photon")
    assert isinstance(photon, jaxrefl.Photon) and photon.photons == scaling.PHOTON["photons"]
    with pytest.raises(ValueError):
        scaling.method_spec("nope")


def test_instrument_times_wrapped_functions():
    """The child's sub-stage timers wrap functions wherever `jaxrefl` modules hold them."""
    from jaxrefl.methods import radiosity
    from jaxrefl.reflectance import fill

    before = (fill.vertex_adjacency, radiosity.vertex_adjacency)
    from jaxrefl.methods.photon import PhotonReplay

    build = vars(PhotonReplay)["build"]
    totals = {}
    undo = scaling._instrument(totals)
    try:
        assert radiosity.vertex_adjacency is fill.vertex_adjacency is not before[0]
        assert isinstance(vars(PhotonReplay)["build"], classmethod) and vars(PhotonReplay)["build"] is not build
        faces = np.array([[0, 1, 2], [0, 2, 3]])
        adj = radiosity.vertex_adjacency(faces, 4)
        assert adj.shape == (4, 4)
        assert totals["vertex adjacency"][0] == 1 and totals["vertex adjacency"][1] >= 0
    finally:  # the originals back for the other tests
        scaling._uninstrument(undo)
    assert vars(PhotonReplay)["build"] is build
    assert (fill.vertex_adjacency, radiosity.vertex_adjacency) == before


def test_rss_and_meminfo_readers():
    assert scaling._rss_bytes() > 10 * MIB
    assert scaling._rss_bytes(2**22 + 12345) == 0  # no such process
    assert scaling.mem_available() > 0
    assert os.path.basename(scaling.scan_path(1000, 6, "/x")) == "bowl_n1000_m6.npz"


def test_resume_reuses_measured_cells():
    todo = scaling.grid(False, ("local",))
    calls = []
    first = scaling.run_grid(todo, _fake_measure(lambda *_: 1.0, calls), 120, 16 * GIB, log=lambda *_: None)
    # an older results file: no `requested_points`, the actual point count instead
    old = [{k: v for k, v in c.items() if k != "requested_points"} for c in first]
    old[0] = dict(old[0], points=10_180)
    previous = scaling.previous_cells(old, todo)
    assert ("local", 10_000, 12) in previous and ("local", 1_000_000, 12) in previous
    again = []
    cells = scaling.run_grid(todo, _fake_measure(lambda *_: 1.0, again), 120, 16 * GIB, log=lambda *_: None,
                             previous=previous)
    assert again == [] and len(cells) == len(todo) and all("error" not in c for c in cells)
    # a skipped cell is measured on resume, and it is not cold: the method has measured cells
    previous.pop(("local", 300_000, 12))
    cells = scaling.run_grid(todo, _fake_measure(lambda *_: 1.0, again), 120, 16 * GIB, log=lambda *_: None,
                             previous=previous)
    assert again == [("local", 300_000, 12, False)]
