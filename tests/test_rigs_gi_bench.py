"""benchmarks.rigs_gi: its pure helpers (errors, the fold's band, the target checks) and the
report written from records (no estimation, no rendering)."""

import json
import math

import numpy as np

from benchmarks import rigs_gi


def test_relative_errors_and_near_fold():
    truth = np.array([[0.5, 0.5, 0.5], [0.2, 0.4, 0.0], [0.0, 0.0, 0.0]])
    est = np.array([[0.55, 0.45, 0.5], [0.3, 0.4, 0.1], [0.1, 0.1, 0.1]])
    err = rigs_gi.relative_errors(est, truth)
    assert math.isclose(err[0], (0.1 + 0.1 + 0.0) / 3)
    assert np.isnan(err[1]) and np.isnan(err[2])  # a channel with truth 0 has no relative error
    np.testing.assert_allclose(rigs_gi.relative_errors([1.1, 0.0], [1.0, 2.0]), [0.1, 1.0])

    d = np.array([0.0, 0.0, 0.005, -0.005, 0.015, -0.019, 0.021, -0.1])
    observed = np.array([True] * 7 + [True])
    observed[4] = False
    near = rigs_gi.near_fold_mask(d, observed)
    # The line's own vertices (0) and the points past 2 cm are out; unobserved points too.
    np.testing.assert_array_equal(near, [False, False, True, True, False, True, False, False])

    s = rigs_gi.summarize(np.array([[0.5] * 3, [0.6] * 3]), np.array([0.3, 0.3]), np.array([0.1, 0.2]),
                          {"pd": np.full((2, 3), 0.5), "ps": np.array([0.3, 0.3]), "roughness": np.array([0.1, 0.1])},
                          np.array([True, True]), near=np.array([False, True]))
    assert math.isclose(s["pd"]["median"], 0.1) and s["pd"]["points"] == 2
    assert s["ps"]["median"] == 0.0 and math.isclose(s["roughness"]["median"], 0.5)
    assert math.isclose(s["pd_near_fold"]["mean"], 0.2) and s["pd_near_fold"]["points"] == 1


def _record(cell="gi_fold_coaxial", obj="fold"):
    def m(pd, ps, rough, warm, near=None, misfit=None):
        e = {"pd": {"median": pd, "p90": pd, "mean": pd, "points": 10},
             "ps": {"median": ps, "p90": ps, "mean": ps, "points": 10},
             "roughness": {"median": rough, "p90": rough, "mean": rough, "points": 10}}
        if near is not None:
            e["pd_near_fold"] = {"median": near, "p90": near, "mean": near, "points": 4}
        out = {"errors": e, "seconds_first": 2 * warm, "seconds_warm": warm, "status": {"measured": 10}}
        if misfit is not None:
            out["misfit"] = {"estimate": misfit, "truth": 1.0, "ratio": misfit}
        return out

    return {"cell": cell, "object": obj, "description": "d", "rig": "coaxial", "material": "grey_gloss",
            "n_points": 10, "observed_points": 10, "observed_share": 1.0, "valid_share": 1.0,
            "lit_share_of_valid": 1.0, "n_lights": 12, "samples": 64, "indirect_share_median": 0.3,
            "indirect_share_p90": 0.6, "mc_relative_stderr_median": 0.02, "render_seconds": 1.0,
            "render_cached": True, "near_fold_points": 4,
            "methods": {"I": m(0.5, 0.9, 0.3, 1.0, near=0.6), "II": m(0.3, 0.2, 0.2, 2.0, near=0.4),
                        "III": m(0.04, 0.05, 0.03, 10.0, near=0.015, misfit=0.95),
                        "auto": {**m(0.043, 0.06, 0.03, 16.0, near=0.015, misfit=0.95),
                                 "auto": {"choice": "photon"}}}}


def test_target_checks():
    checks = {c["check"]: c for c in rigs_gi.target_checks(_record())}
    fold = checks["III: mean pd error within 2 cm of the fold <= 2 %"]
    assert fold["value"] == 0.015 and fold["met"] is True
    assert checks["III: misfit ratio <= 1.1"]["met"] is True
    pd = checks["auto: median pd error <= 1.1x the best single method's"]
    assert math.isclose(pd["value"], 0.043 / 0.04) and pd["met"] is True and pd["context"] == "best III"
    ps = checks["auto: median ps error <= 1.1x the best single method's"]
    assert math.isclose(ps["value"], 0.06 / 0.05) and ps["met"] is False
    t = checks["auto: time <= 1.5x the best single method's (by pd)"]
    assert math.isclose(t["value"], 1.6) and t["met"] is False
    assert not any("bowl" in k for k in checks)

    rec = _record("gi_bowl", "bowl")
    rec["methods"]["III"]["errors"]["roughness"]["median"] = 0.12
    del rec["methods"]["III"]["misfit"]
    bowl = {c["check"]: c for c in rigs_gi.target_checks(rec)}
    assert bowl["III: median pd error <= 3%"]["met"] is False  # 4 %
    assert bowl["III: median ps error <= 10%"]["met"] is True
    assert bowl["III: median roughness error <= 10%"]["met"] is False
    assert bowl["III: misfit ratio <= 1.1"]["met"] is None  # no number: not claimed either way
    assert not any("fold" in k for k in bowl)

    rec = _record()
    rec["methods"]["III"] = {"error": "RuntimeError: boom"}
    after = {c["check"]: c for c in rigs_gi.target_checks(rec)}
    assert after["III: mean pd error within 2 cm of the fold <= 2 %"]["met"] is None
    assert after["auto: median pd error <= 1.1x the best single method's"]["context"] == "best II"


def test_report_from_records(tmp_path):
    run = {"command": "python3 -m benchmarks.rigs_gi", "date": "2026-01-01T00:00:00", "nproc": 2,
           "platform": "linux", "python": "3.11", "jax": "0", "source_hash": "abc", "seed": 0, "n_points": None,
           "complete": True, "seconds": 60.0, "load_start": 1.0, "load_end": 1.0,
           "photon": {"photons": 1000, "iterations": 2}}
    out = tmp_path / "R.md"
    (tmp_path / "R.md").write_text("# old\n\n## Findings\n\nBy hand.\n\n## Cells\n")
    rigs_gi.write_report([_record(), {"cell": "gi_cup", "error": "ValueError: x"}], run, out)
    text = out.read_text()
    assert "gi_fold_coaxial" in text and "FAILED" in text and "## Targets:" in text
    assert "By hand." in text and text.count("## Findings") == 1  # the hand-written section is kept
    data = json.loads(out.with_suffix(".json").read_text())
    assert data["cells"][0]["cell"] == "gi_fold_coaxial" and data["checks"]
    again = tmp_path / "again.md"
    rigs_gi.render_report(out.with_suffix(".json"), again)
    assert "## Targets:" in again.read_text()


def test_run_cell_plumbing(tmp_path, monkeypatch):
    """run_cell on a small GI cell with stand-in estimators (truth plus a known error): the errors,
    the warm runs (none for the once-only `III defaults`) and a failing method are recorded."""
    from types import SimpleNamespace

    monkeypatch.setenv("JAXREFL_ZOO_CACHE", str(tmp_path))

    def fake(scale, meta=None):
        def run(scan, caster):
            return SimpleNamespace(pd=scan.true_pd * scale, ps=scan.true_ps, roughness=scan.true_alpha * 2,
                                   status=np.zeros(scan.n_points, np.int8), meta=dict(meta or {}))
        return run

    def broken(scan, caster):
        raise RuntimeError("boom")

    misfit = {"misfit": {"estimate": 1.0, "truth": 1.0, "ratio": 1.0}, "seconds": {"trace": 0.1}}
    monkeypatch.setattr(rigs_gi, "_methods", lambda photon: {
        "I": fake(1.1), "II": broken, "III": fake(1.01, misfit), "auto": fake(1.01, misfit),
        rigs_gi.DEFAULTS: fake(1.0, misfit), rigs_gi.PRIOR: fake(1.02, misfit)})
    logs = []
    rec = rigs_gi.run_cell("gi_bumpy_ring", n_points=162, methods=rigs_gi.METHODS + (rigs_gi.DEFAULTS,),
                           log=logs.append)
    m = rec["methods"]
    assert math.isclose(m["I"]["errors"]["pd"]["median"], 0.1)
    assert math.isclose(m["I"]["errors"]["roughness"]["median"], 1.0)
    assert "boom" in m["II"]["error"] and m["III"]["misfit"]["ratio"] == 1.0
    assert "seconds_warm" in m["III"] and "seconds_warm" not in m[rigs_gi.DEFAULTS]
    assert "seconds_warm" not in m[rigs_gi.PRIOR] and math.isclose(m[rigs_gi.PRIOR]["errors"]["pd"]["median"], 0.02)
    assert m["III"]["status"] == {"measured": 162} and len(logs) == 7
    checks = {c["check"]: c for c in rigs_gi.target_checks(rec)}
    assert checks["auto: median pd error <= 1.1x the best single method's"]["context"] == "best III"


def test_interreflected_points():
    clean = np.array([[[1.0] * 3, [1.0] * 3, [2.0] * 3], [[1.0] * 3, [0.0] * 3, [1.0] * 3], [[1.0] * 3] * 3])
    direct = np.array([[[0.8] * 3, [0.85] * 3, [2.0] * 3], [[1.0] * 3, [0.0] * 3, [0.95] * 3], [[1.0] * 3] * 3])
    seen = np.array([[True, True, True], [True, True, True], [False, False, False]])
    # Shares: point 0 (0.2, 0.15, 0) -> median 0.15; point 1 (0, -, 0.05) -> 0.025; point 2 never seen.
    np.testing.assert_array_equal(rigs_gi.interreflected_points(clean, direct, seen), [True, False, False])
    np.testing.assert_array_equal(rigs_gi.interreflected_points(clean, direct, seen, share=0.02), [True, True, False])
