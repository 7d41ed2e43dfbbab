"""benchmarks.pareto: the Pareto front on a hand-made example, light subsets, and the
bench's core end to end on a tiny scene (real render, real Method I and II runs)."""

import dataclasses
import json
import math
import types

import numpy as np

from benchmarks import pareto
from jaxrefl.scan.io import Scan


def test_pareto_front_hand_made():
    #            fast+bad  dominated  middle  tie(t)  slow+best  dup of middle  NaN
    seconds = [0.1, 0.5, 0.4, 0.4, 10.0, 0.4, np.nan]
    errors = [0.30, 0.31, 0.10, 0.12, 0.01, 0.10, 0.001]
    front = pareto.pareto_front(seconds, errors)
    # 0.5 s / 31 % is beaten by 0.1 s / 30 %; 0.4 s / 12 % by 0.4 s / 10 %; equal points both stay;
    # a point without a time is never on the front.
    assert front.tolist() == [True, False, True, False, True, True, False]
    assert pareto.pareto_front([1.0], [0.5]).tolist() == [True]


def test_subset_lights_keeps_observations():
    n, m = 4, 5
    rng = np.random.default_rng(0)
    scan = Scan(vertices=rng.normal(size=(n, 3)), faces=np.zeros((1, 3), int), light_pos=rng.normal(size=(n, m, 3)),
                cam_pos=rng.normal(size=(n, 1, 3)), light_intensity=np.arange(1.0, m + 1),
                radiance=rng.random((n, m, 3)), valid=rng.random((n, m)) > 0.3)
    sub = pareto.subset_lights(scan, [0, 2])
    assert sub.n_lights == 2
    np.testing.assert_array_equal(sub.light_pos, scan.light_pos[:, [0, 2]])
    np.testing.assert_array_equal(sub.radiance, scan.radiance[:, [0, 2]])
    np.testing.assert_array_equal(sub.valid, scan.valid[:, [0, 2]])
    np.testing.assert_array_equal(sub.light_intensity, [1.0, 3.0])
    assert sub.cam_pos.shape == (n, 1, 3)  # one camera per point: not indexed by light
    rack = pareto.subset_lights(dataclasses.replace(scan, light_pos=scan.light_pos[0], cam_pos=scan.light_pos[0]),
                                [4, 1])
    np.testing.assert_array_equal(rack.light_pos, scan.light_pos[0, [4, 1]])
    np.testing.assert_array_equal(rack.cam_pos, scan.light_pos[0, [4, 1]])


def test_bench_core_writes_table_plot_json(tmp_path):
    cfg = types.SimpleNamespace(resolution=16, resolution_e=24, samples=2, samples_e=4, seed=1, repeats=1,
                                command="python3 -m benchmarks.pareto (test)")
    sweep = [pareto.Setting("local", "ward"), pareto.Setting("radiosity")]
    res = pareto.run_bench(["E glossy"], sweep, cfg, log=lambda s: None)
    paths = pareto.write_outputs(res, str(tmp_path / "RESULTS.md"))

    (scene,) = res["scenes"]
    assert [r["label"] for r in scene["rows"]] == ["I Ward", "II"]
    for r in scene["rows"]:
        assert r["first_s"] > 0 and len(r["warm_s"]) == 1 and r["seconds"] > 0
        for m in ("pd", "ps", "fold"):
            assert math.isfinite(r["errors"][m]) and r["errors"][m] >= 0, (r["label"], m)
        assert r["errors"]["pd"] < 0.5
    for m in ("pd", "ps", "fold"):  # the marks agree with the front function on the measured numbers
        want = pareto.pareto_front([r["seconds"] for r in scene["rows"]], [r["errors"][m] for r in scene["rows"]])
        assert [r["front"][m] for r in scene["rows"]] == want.tolist()
        assert want.any()

    with open(paths["json"]) as fh:
        raw = json.load(fh)  # strict JSON: no NaN
    assert raw["scenes"][0]["rows"][1]["errors"] == scene["rows"][1]["errors"]
    md = open(paths["md"]).read()
    assert "python3 -m benchmarks.pareto (test)" in md and "Load average" in md and "median of 1 warm" in md
    assert f"| I Ward | {len(scene['lights'])} |" in md and f"| II | {len(scene['lights'])} |" in md
    assert "Pareto front, median rel. pd error" in md
    png = open(paths["png"], "rb").read()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
