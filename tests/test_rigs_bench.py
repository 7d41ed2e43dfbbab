"""benchmarks.rigs: the per-cell record of one small zoo cell has its keys and finite numbers
(no timing asserts: the machine is shared)."""

import json
import math

import numpy as np

from benchmarks import rigs


def _finite_number(x):
    return isinstance(x, (int, float)) and math.isfinite(x)


def test_run_cell_record_small_cell(tmp_path):
    # The default variant only: the test's time is nearly all XLA compilation, and `gates` and
    # `paper` compile their own stages (the full benchmark runs them).
    rec = rigs.run_cell("sparse_uniform", seed=0, n_points=162, fraction=0.25, models=("ward",),
                        variants=("prior",), repeat=False, log=lambda s: None)
    for key in ("cell", "n_points", "n_lights", "fit_lights", "held_out_lights", "visible_share",
                "observed_share", "truth_floor", "noise_floor", "models", "seconds"):
        assert key in rec, key
    assert rec["n_points"] == 162 and rec["fit_lights"] + len(rec["held_out_lights"]) == rec["n_lights"]
    assert _finite_number(rec["truth_floor"]["rel_rms"]) and _finite_number(rec["noise_floor"]["rel_rms"])
    # The truth's own relighting and the noise-free render give the same floor.
    assert np.isclose(rec["truth_floor"]["rel_rms"], rec["noise_floor"]["rel_rms"], rtol=1e-6)
    m = rec["models"]["ward"]
    assert m["matched"] is True
    for key in ("plain", "reference"):
        assert "error" not in m[key], m[key].get("error")
        assert _finite_number(m[key]["holdout"]["rel_rms"])
        assert _finite_number(m[key]["errors"]["pd"]["all"])
    assert m["reference"]["lobes"] and _finite_number(m["reference"]["lobes"][0]["ps"])
    assert set(m["variants"]) == {"prior"}
    for name, v in m["variants"].items():
        assert "error" not in v, (name, v.get("error"))
        for key in ("seconds_first", "errors", "coverage", "coverage_observed", "holdout", "calibration",
                    "ratio_truth_floor", "ratio_reference", "ratio_plain"):
            assert key in v, (name, key)
        assert "seconds_second" not in v  # repeat=False
        for p in ("pd", "ps", "roughness"):
            assert _finite_number(v["errors"][p]["all"]), (name, p)
        assert _finite_number(v["holdout"]["rel_rms"]) and _finite_number(v["holdout"]["median_rel"])
        assert _finite_number(v["ratio_truth_floor"]) and _finite_number(v["ratio_reference"])
        assert math.isclose(sum(v["coverage"].values()), 1.0)
    # The report and its JSON are written from the record.
    args = rigs.argparse.Namespace(seed=0, n_points=162, holdout=0.25)
    out = tmp_path / "RESULTS_rigs.md"
    run = rigs.run_info(args, "python3 -m benchmarks.rigs --cells sparse_uniform", 1.0, True)
    rigs.write_report([rigs._sanitise(rec), {"cell": "broken", "error": "ValueError: boom"}], run, out)
    text = out.read_text()
    assert "sparse_uniform" in text and "Must-shows" in text and "boom" in text and "nproc" in text
    def no_nan(name):
        raise AssertionError(f"{name} in the JSON")

    data = json.loads(out.with_suffix(".json").read_text(), parse_constant=no_nan)
    assert data["cells"][0]["cell"] == "sparse_uniform" and data["must_shows"]
    again = tmp_path / "again.md"
    rigs.render_report(out.with_suffix(".json"), again)
    assert again.read_text().split("- Date")[1] == text.split("- Date")[1]


def test_failing_variant_is_recorded(monkeypatch):
    def boom(model, variant):
        if variant == "gates":
            raise RuntimeError("broken estimator")
        return rigs._options_real(model, variant)

    monkeypatch.setattr(rigs, "_options_real", rigs._options, raising=False)
    monkeypatch.setattr(rigs, "_options", boom)
    rec = rigs.run_cell("sparse_uniform", seed=0, n_points=162, models=("ward",), variants=("gates", "prior"),
                        repeat=False, log=lambda s: None)
    v = rec["models"]["ward"]["variants"]
    assert "broken estimator" in v["gates"]["error"]
    assert "error" not in v["prior"] and _finite_number(v["prior"]["holdout"]["rel_rms"])
    assert any(s["check"] == "held-out rel-RMS <= 1.5x truth floor" for s in rigs.must_shows([rec]))


def test_material_visible_and_the_scope_of_the_lobe_targets():
    """A material counts where any of its points shows its lobe; the ps and roughness checks
    are taken over those materials' points, pd over all."""
    labels = np.array([0, 0, 1, 1, 2])
    visible = np.array([False, True, False, False, False])
    np.testing.assert_array_equal(rigs.material_visible(labels, visible), [True, True, False, False, False])
    errors = {"pd": {"all": 0.002, "observed": 0.002},
              "ps": {"all": 0.5, "observed": 0.5, "lobe_seen": 0.01},
              "roughness": {"all": 0.5, "observed": 0.5, "lobe_seen": 0.2}}
    rec = {"cell": "c", "brdf": "ward", "models": {"ward": {"matched": True, "variants": {
        "prior": {"errors": errors, "ratio_truth_floor": 1.0}}}}}
    checks = {c["check"].split(" error")[0]: c for c in rigs.must_shows([rec])}
    assert checks["median pd"]["met"] and checks["median pd"]["value"] == "0.20%"
    assert checks["median ps"]["met"] and "all points: 50.00%" in checks["median ps"]["context"]
    assert not checks["median roughness"]["met"] and checks["median roughness"]["value"] == "20.00%"
