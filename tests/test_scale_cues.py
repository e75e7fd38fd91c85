"""The metric scale from several cues by frame range (paradrive.ingest.scalecue and its cue
modules), the drift taken out of a path and the runs split where it jumps: fast, no SfM."""

from __future__ import annotations

import math

import numpy as np
import pytest

from paradrive.ingest import scale_roadmotion, scale_roadpoints
from paradrive.ingest.roadmotion import summarise
from paradrive.ingest.scalecue import ScaleCue, ScaleError, combine, profile, split_ranges
from paradrive.ingest.sfm import Reconstruction, RoadPlane, Intrinsics, without_drift
from paradrive.stages.ingest import params_of

HALVES = [(0, 49), (50, 99)]
BIAS = params_of().video_road_points_bias   # the stage file's default


def cue(name: str, frames: tuple[int, int], scale: float | None, sigma: float = math.inf,
        why: str = "") -> ScaleCue:
    return ScaleCue(name, frames, scale, sigma, why=why)


def test_ranges_are_halves_of_at_least_the_minimum():
    assert split_ranges(100, 16, 2) == HALVES
    assert split_ranges(51, 16, 2) == [(0, 25), (26, 50)]
    assert split_ranges(20, 16, 2) == [(0, 19)]


def test_agreeing_cues_are_weighed_by_their_uncertainties():
    cues = [cue("a", r, 2.0, 0.01) for r in HALVES] + [cue("b", r, 2.02, 0.03) for r in HALVES]
    found = combine(cues, HALVES)
    w = np.array([1 / 0.01 ** 2, 1 / 0.03 ** 2])
    assert found.scale == pytest.approx(math.exp(w @ np.log([2.0, 2.02]) / w.sum()))
    assert found.ranges[0].birge == 1.0 and found.ranges[0].uncertainty < 0.01
    # the ranges' uncertainties add up linearly (a cue's bias has one sign in every range)
    assert found.uncertainty == pytest.approx(found.ranges[0].uncertainty)
    assert found.weight_of("a") == pytest.approx(0.9)


def test_cues_that_scatter_more_than_they_say_widen_the_uncertainty():
    cues = [cue("a", (0, 99), 2.0, 0.01), cue("b", (0, 99), 2.05, 0.01)]
    found = combine(cues, [(0, 99)])
    chi = abs(math.log(2.05 / 2.0)) / 0.01 / math.sqrt(2)   # sqrt(chi2 / dof) of two cues
    assert found.ranges[0].birge == pytest.approx(chi)
    assert found.uncertainty == pytest.approx(0.01 / math.sqrt(2) * chi)


def test_a_cue_that_fails_on_a_range_is_replaced_by_another_there():
    cues = [cue("road motion", HALVES[0], None, why="fewer than 5 frame pairs aligned"),
            cue("road motion", HALVES[1], 2.0, 0.01),
            cue("road points", HALVES[0], 2.2, 0.03), cue("road points", HALVES[1], 2.04, 0.03)]
    found = combine(cues, HALVES)
    assert found.ranges[0].carried_by == ["road points"] and found.ranges[0].scale == pytest.approx(2.2)
    assert found.ranges[1].carried_by == ["road motion", "road points"]
    assert found.parts["between_ranges"] == pytest.approx(math.log(2.2 / found.ranges[1].scale) / 2)


def test_a_range_no_cue_measured_takes_its_neighbours_scale_and_their_drift():
    ranges = [(0, 19), (20, 39), (40, 59)]
    cues = [cue("a", ranges[0], 2.0, 0.01), cue("a", ranges[1], None, why="no road"),
            cue("a", ranges[2], 2.2, 0.01)]
    found = combine(cues, ranges)
    middle = found.ranges[1]
    assert middle.filled_in and middle.scale == pytest.approx(math.sqrt(2.0 * 2.2))
    assert middle.uncertainty == pytest.approx(math.hypot(0.01, math.log(2.2 / 2.0) / 2))


def test_no_cue_anywhere_names_every_reason():
    cues = [cue("road motion", (0, 99), None, why="fewer than 5 frame pairs aligned"),
            cue("road points", (0, 99), None, why="no road plane")]
    with pytest.raises(ScaleError) as info:
        combine(cues, [(0, 99)])
    text = str(info.value)
    assert "road motion over frames 0-99: fewer than 5 frame pairs aligned" in text
    assert "road points over frames 0-99: no road plane" in text


def test_cues_that_contradict_each_other_are_refused_naming_them():
    cues = [cue("road motion", (0, 99), 2.0, 0.01), cue("road points", (0, 99), 2.4, 0.03)]
    with pytest.raises(ScaleError) as info:
        combine(cues, [(0, 99)])
    text = str(info.value)
    assert "over frames 0-99" in text and "road motion gives 2 m a unit (±1.0%)" in text
    assert "road points 2.4 (±3.0%)" in text and "18.2% apart" in text


def test_common_uncertainties_add_in_quadrature():
    found = combine([cue("a", (0, 99), 2.0, 0.03)], [(0, 99)], common={"focal": 0.04})
    assert found.uncertainty == pytest.approx(0.05)


def test_the_profile_is_piecewise_linear_in_log_scale_between_range_middles():
    cues = [cue("a", HALVES[0], 2.0, 0.01), cue("a", HALVES[1], 2.4, 0.01)]
    found = combine(cues, HALVES, lengths=[1.0, 1.0])
    ratio = profile(found, 100)
    assert found.scale == pytest.approx(2.2)
    assert ratio[0] == pytest.approx(2.0 / 2.2) and ratio[-1] == pytest.approx(2.4 / 2.2)
    assert ratio[49] * 2.2 == pytest.approx(math.exp(math.log(2.0) + 0.49 * math.log(1.2)), rel=1e-3)


def reconstruction(c2w: np.ndarray, points: np.ndarray, point_frame: np.ndarray) -> Reconstruction:
    return Reconstruction(c2w=c2w, points=points, colors=np.zeros((len(points), 3), np.uint8),
                          point_frame=point_frame, point_views=np.full(len(points), 3),
                          intrinsics=Intrinsics(100, 100, 50, 50), distortion=(0.0,) * 5,
                          estimated=False, seconds=0.0)


def test_the_drift_is_taken_out_of_the_steps_and_the_points():
    """A straight drive of even 1 m steps whose model scale drifts from 1 to 2 units a metre:
    stretched by its scale's profile, the steps are even again and each point keeps its place
    relative to the camera that first saw it, in metres."""
    n = 21
    units = np.linspace(1.0, 2.0, n)          # model units per metre at each frame
    steps = 0.5 * (units[1:] + units[:-1])
    c2w = np.repeat(np.eye(4)[None], n, axis=0)
    c2w[:, 2, 3] = np.r_[0.0, np.cumsum(steps)]
    points = c2w[:, :3, 3] + np.array([0.0, 1.5, 4.0]) * units[:, None]   # 4 m ahead, 1.5 m down
    ratio = (1 / units) / np.mean(1 / units)  # metres a unit at each frame over the mean
    rec = without_drift(reconstruction(c2w, points, np.arange(n)), 0, ratio)
    metres = rec.c2w[:, :3, 3] / np.mean(1 / units) ** -1
    np.testing.assert_allclose(np.diff(metres[:, 2]), 1.0, rtol=2e-3)
    offsets = (rec.points - rec.c2w[:, :3, 3]) / np.mean(1 / units) ** -1
    np.testing.assert_allclose(offsets, np.tile([0.0, 1.5, 4.0], (n, 1)), rtol=1e-9, atol=1e-9)


def test_the_road_points_cue_counts_its_bias_beside_its_scatter():
    depths = np.r_[np.full(20, 0.5), np.full(20, 0.55)]
    plane = RoadPlane(np.array([0.0, 0.0, 1.0]), 0.0, 0.525, 40, 100, depths=depths,
                      frames=np.r_[np.arange(20), np.arange(20) + 50])
    first = scale_roadpoints.measure(plane, (0, 49), 1.5, bias=BIAS)
    assert first.scale == pytest.approx(3.0)
    assert first.uncertainty == pytest.approx(BIAS)  # no scatter there
    # frames counted from the kept run's first frame
    second = scale_roadpoints.measure(plane, (40, 89), 1.5, offset=10, bias=BIAS)
    assert second.scale == pytest.approx(1.5 / 0.55) and second.figures["points"] == 20
    assert scale_roadpoints.measure(plane, (0, 9), 1.5, bias=BIAS).scale is None


def test_the_road_motion_cue_is_measured_on_the_pairs_of_its_range():
    heights = np.r_[np.full(8, 0.5), np.full(8, 0.6)]
    pairs = [(i, i + 3) for i in range(0, 80, 5)]
    motion = summarise(heights, heights, heights, pairs, 5)
    assert motion is not None
    first = scale_roadmotion.measure(motion, (0, 39), 1.5)
    assert first.scale == pytest.approx(3.0) and first.figures["pairs"] == 8
    assert scale_roadmotion.measure(motion, (40, 79), 1.5).scale == pytest.approx(2.5)
    assert scale_roadmotion.measure(motion, (76, 79), 1.5).scale is None
    assert scale_roadmotion.measure(None, (0, 79), 1.5).why


def test_a_run_is_split_where_the_camera_s_step_jumps():
    """Even 1 m steps with three frames SfM placed 5 m on: the run splits around them, and the
    longest steady run is the one after; a standstill's noise and a start (steps growing by
    half a frame) do not split."""
    from paradrive.ingest.sfm import steady_runs

    steps = np.r_[np.full(20, 1.0), [5.0, 5.0, 5.0], np.full(30, 1.0)]
    c2w = np.repeat(np.eye(4)[None], len(steps) + 1, axis=0)
    c2w[:, 2, 3] = np.r_[0.0, np.cumsum(steps)]
    runs = steady_runs(c2w, [(0, len(steps))])
    assert runs == [(0, 20), (20, 23), (23, 53)]
    smooth = np.r_[0.001, 0.003, 0.0005, 0.01 * 1.5 ** np.arange(16)]
    c2w = np.repeat(np.eye(4)[None], len(smooth) + 1, axis=0)
    c2w[:, 2, 3] = np.r_[0.0, np.cumsum(smooth)]
    assert steady_runs(c2w, [(0, len(smooth))]) == [(0, len(smooth))]


def test_a_variable_rate_videos_longer_intervals_are_not_jumps():
    """A constant 10 m/s drive whose video lost frames 5-6 and 12-13 (0.3 s intervals among the
    0.1 s ones): the steps there are three times the others, the speed is not, so the run holds
    with the frames' times and would split at each gap without them."""
    from paradrive.ingest.sfm import steady_runs

    times = np.array([t for t in np.arange(24) / 10.0 if round(t * 10) not in (5, 6, 12, 13)])
    c2w = np.repeat(np.eye(4)[None], len(times), axis=0)
    c2w[:, 2, 3] = 10.0 * times
    whole = [(0, len(times) - 1)]
    assert steady_runs(c2w, whole, times=times) == whole
    assert len(steady_runs(c2w, whole)) > 1
