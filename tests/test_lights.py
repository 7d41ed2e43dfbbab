"""Greedy light selection against constructed instances and the exact integer program."""

import numpy as np
import pytest

from jaxrefl.capture.select import coverage, exact_minimum, select_lights


def constructed():
    """8 points, 6 lights. Diffuse: light 0 covers points 0-4, light 1 points 5-7.
    Specular: lights 2 and 3 each cover every point, light 4 covers points 0-3,
    light 5 nothing. Optimum: {0, 1, 2, 3}."""
    d = np.zeros((8, 6), bool)
    s = np.zeros((8, 6), bool)
    d[:5, 0] = True
    d[5:, 1] = True
    d[:2, 4] = True
    s[:, 2] = s[:, 3] = True
    s[:4, 4] = True
    return d, s


def test_constructed_instance_known_answer():
    d, s = constructed()
    sel = select_lights(d, s)
    assert sel.selected == [0, 2, 1, 3]
    assert [c["criterion"] for c in sel.curve] == ["diffuse", "specular", "diffuse", "specular"]
    assert sel.diffuse_only_count == 3
    assert sel.diffuse_coverage == sel.specular_coverage == 1.0
    assert [c["specular_coverage"] for c in sel.curve] == [0.0, 0.0, 0.0, 1.0]
    exact = exact_minimum(d, s)
    assert exact["count"] == 4 and sorted(exact["selected"]) == [0, 1, 2, 3]


def test_marginal_gain_avoids_redundant_picks_that_raw_counts_make():
    """Raw counts (the paper) re-pick a light that covers already-covered points."""
    d = np.zeros((10, 5), bool)
    s = np.zeros((10, 5), bool)
    d[:6, 0] = d[:6, 1] = True  # lights 0 and 1 are twins
    d[6:, 2] = True
    s[:, 3] = s[:, 4] = True
    paper = select_lights(d, s, marginal=False, target=1.0)
    ours = select_lights(d, s, target=1.0)
    assert ours.selected == [0, 3, 2, 4]
    assert paper.selected == [0, 3, 1, 4, 2]
    assert ours.diffuse_coverage == 1.0


def test_stops_at_target_with_no_spare_light():
    rng = np.random.default_rng(0)
    d = rng.uniform(size=(400, 30)) < 0.05
    s = rng.uniform(size=(400, 30)) < 0.15
    sel = select_lights(d, s, target=0.9)
    assert sel.specular_coverage >= 0.9 * sel.specular_coverage_all
    assert sel.diffuse_coverage == pytest.approx(sel.diffuse_coverage_all)
    # Without the last light the goal was not met yet.
    cd, cs = coverage(d, s, sel.selected[:-1])
    assert cd < sel.diffuse_coverage_all or cs < 0.9 * sel.specular_coverage_all


def test_exact_minimum_is_feasible_and_never_worse_than_greedy():
    rng = np.random.default_rng(1)
    for trial in range(3):
        d = rng.uniform(size=(150, 16)) < 0.1
        s = rng.uniform(size=(150, 16)) < 0.25
        greedy = select_lights(d, s, target=1.0)
        exact = exact_minimum(d, s)
        assert exact["status"] == "optimal"
        assert exact["count"] <= len(greedy.selected)
        cd, cs = coverage(d, s, exact["selected"])
        assert cd == pytest.approx(greedy.diffuse_coverage_all)
        assert cs == pytest.approx(greedy.specular_coverage_all)
        partial = exact_minimum(d, s, target=0.8)
        assert partial["count"] <= exact["count"]
        assert coverage(d, s, partial["selected"])[1] >= 0.8 * greedy.specular_coverage_all - 1e-12


def test_unseen_points_do_not_count():
    d, s = constructed()
    seen = np.ones(8, bool)
    seen[5:] = False
    sel = select_lights(d, s, seen=seen)
    assert 1 not in sel.selected and sel.seen_points == 5


def test_shape_mismatch_is_refused():
    with pytest.raises(ValueError, match="strong_specular"):
        select_lights(np.zeros((3, 2), bool), np.zeros((3, 3), bool))


def test_weights_count_image_share_not_points():
    """With weights, a light covering few heavy points beats one covering many light ones."""
    d = np.zeros((4, 3), bool)
    s = np.zeros((4, 3), bool)
    d[:3, 0] = True  # three points of weight 1
    d[3, 1] = True  # one point of weight 10
    d[:, 2] = False
    s[:, :] = True
    w = np.array([1.0, 1.0, 1.0, 10.0])
    sel = select_lights(d, s, weights=w, target=1.0)
    assert sel.curve[0]["light"] == 1 and sel.curve[0]["diffuse_coverage"] == pytest.approx(10 / 13)
    assert coverage(d, s, [0], weights=w)[0] == pytest.approx(3 / 13)
    exact = exact_minimum(d, s, weights=w, target=0.5)
    assert exact["count"] >= 2  # diffuse needs both 0 and 1, specular any two
    with pytest.raises(ValueError, match="weights"):
        select_lights(d, s, weights=-w)
