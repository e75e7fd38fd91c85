"""The focal length of an uncalibrated camera (paradrive.ingest.focal): where the reprojection
error's curve over the candidate focals places it, and when it says nothing. Fast: the trials
are made up; tests/test_video_kitti.py runs the search on real frames."""

from __future__ import annotations

import math

import pytest

from paradrive.ingest import focal


def made_up(curve, focals) -> list[focal.FocalTrial]:
    return [focal.FocalTrial(f, 26, curve(f), 1.0, 1000) for f in focals]


def test_the_focal_search_places_the_parabola_s_vertex_and_measures_its_depth():
    true = 370.0
    trials = [focal.FocalTrial(f, 26, 0.35 + 3.0 * math.log(f / true) ** 2, 1.0)
              for f in (300.0, 340.0, 360.0, 380.0, 420.0, 600.0)]
    found, spread = focal._vertex(trials)
    assert found == pytest.approx(true, rel=1e-6) and spread == pytest.approx(0.0, abs=1e-6)
    best = min(trials, key=lambda t: t.error)
    # one coarse step (x1.5) away the error is far above the flat curve of a straight drive
    assert focal._rise(trials, best, 1.5) > 0.5
    flat = [focal.FocalTrial(f, 26, 0.44 + 0.001 * (f == 500.0), 1.0) for f in (300.0, 400.0, 500.0, 650.0)]
    assert focal._rise(flat, min(flat, key=lambda t: t.error), 1.3) < 0.01
    assert focal.focal_of_fov(640, 90.0) == pytest.approx(320.0)


def test_a_curve_with_one_basin_inside_the_range_is_measured_and_others_are_not():
    grid = [185.0, 295.0, 470.0, 749.0, 1194.0]
    bend = made_up(lambda f: 0.35 + 1.5 * math.log(f / 370.0) ** 2, grid)
    assert focal._one_basin(bend)
    # falling all the way to the widest field of view: the focal may lie beyond the range
    assert not focal._one_basin(made_up(lambda f: 0.3 + f / 5000, grid))
    # two minima: the reconstruction jumped between trials, not the fit of the focal
    jumpy = made_up(lambda f: {185.0: 0.37, 295.0: 0.54, 470.0: 0.36, 749.0: 0.58, 1194.0: 0.66}[f], grid)
    assert not focal._one_basin(jumpy)


def test_a_trial_that_dropped_part_of_the_scene_counts_as_failed():
    made = [focal.FocalTrial(f, 30, 0.55, 1.0, points) for f, points in
            ((134.0, 928), (160.0, 919), (343.0, 457), (440.0, 719))]
    kept = focal._plausible(made)
    assert [math.isinf(t.error) for t in kept] == [False, False, True, False]
    assert kept[2].points == 457 and kept[2].focal == 343.0
