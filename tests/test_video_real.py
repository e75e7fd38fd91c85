"""The video: input on a real dashcam clip (../shared/realdata/udacity-freeway: 160 frames of a
California freeway at 1280x720, a lens with k1 = -0.26, the hood, cars ahead, tree shadows):
every frame registers, the distance driven agrees with the clip's own dash ruler within 3 %
and within two of the scale's reported uncertainties, the frames are stored undistorted, and
a smoke build publishes pairs; its moving masks cover its cars and not its road, its ego mask
is its hood. Skipped where the clip is not there."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from conftest import FREEWAY, FREEWAY_VIDEO
from paradrive.contracts.layout import SceneLayout
from paradrive.scene import read_image

pytestmark = pytest.mark.slow

# The clip's ruler, measured on its undistorted frames by bench/bench_video.py --write-ruler:
# when the lane dashes' near ends pass fixed image rows (frame times), in runs of whole
# Caltrans periods (14.63 m); docs/scene-layout.md, "A real freeway clip"
RULER = json.loads((Path(__file__).parent / "udacity_freeway_ruler.json").read_text())
LABELS = Path(__file__).resolve().parent / "udacity_freeway_cars.json"


def scene_of(build) -> tuple[dict, Path]:
    (scene_dir,) = (build["data_dir"] / "scenes").iterdir()
    return json.loads((scene_dir / "scene.json").read_text()), scene_dir


def path_error(c2w: np.ndarray) -> tuple[float, list[float]]:
    """The scene's path between each ruler run's first and last passage over the run's periods
    (all runs summed), and each run's own."""
    centres = c2w[:, :3, 3]
    along = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(centres, axis=0), axis=1))]
    frames = np.arange(len(along))
    runs = [(np.interp(s["last"], frames, along) - np.interp(s["first"], frames, along),
             s["periods"] * RULER["period_m"]) for s in RULER["segments"]]
    return sum(a for a, _ in runs) / sum(b for _, b in runs) - 1, [a / b - 1 for a, b in runs]


def test_every_frame_of_the_clip_registers_with_the_calibrated_camera(freeway_build):
    scene, _ = scene_of(freeway_build)
    video = scene["video"]
    cal = json.loads((FREEWAY / "calibration.json").read_text())
    assert video["registered"] == "0-159" and len(scene["frames"]) == 160
    assert video["native_fps"] == 25 and video["skipped_frames"] == 0
    intr = video["intrinsics"]
    # the pinhole after undistortion, pixel centres at +0.5; the lens model it was undistorted by
    assert (intr["fx"], intr["fy"]) == (cal["fx"], cal["fy"])
    assert (intr["cx"], intr["cy"]) == (cal["cx"] + 0.5, cal["cy"] + 0.5)
    assert intr["undistorted"] and intr["distortion"] == [cal[k] for k in ("k1", "k2", "p1", "p2", "k3")]
    assert not intr["estimated"] and intr["given_by"] == str(FREEWAY / "calibration.json")
    assert video["sfm"]["downscaled"] and (video["sfm"]["width"], video["sfm"]["height"]) == (640, 360)


def test_the_distance_driven_agrees_with_the_dash_ruler(freeway_build):
    """Within 3 % over the ruler's runs (about 146 m each row), and within two of the scale's
    reported uncertainties, with only the camera height given."""
    from paradrive.scene import load_scene

    scene, scene_dir = scene_of(freeway_build)
    scale = scene["video"]["scale"]
    assert scale["height_from"] == "road motion" and scale["road_motion"]["pairs"] >= 30
    error, runs = path_error(load_scene(scene_dir).c2w("front"))
    assert abs(error) < 0.03, (error, runs)
    assert abs(error) < 2 * scale["uncertainty"] or abs(error) < 0.005, (error, scale["uncertainty"])
    assert max(abs(e) for e in runs) < 0.03, runs   # each run of dashes on its own too


def test_the_scale_s_uncertainty_is_recorded_and_accepted(freeway_build):
    scene, _ = scene_of(freeway_build)
    scale = scene["video"]["scale"]
    assert 0 < scale["uncertainty"] < 0.05
    # both halves measured by both cues; the road's motion, the surer one, carries the scale
    assert [r["carried_by"] for r in scale["ranges"]] == [["road motion", "road points"]] * 2
    assert scale["weights"]["road motion"] > 0.5
    # the calibrated camera adds no focal part: the halves' uncertainties, weighted by their
    # lengths and summed, are the whole figure
    assert "focal" not in scale["parts"]
    assert scale["uncertainty"] == pytest.approx(scale["parts"]["ranges"])
    assert min(r["uncertainty"] for r in scale["ranges"]) <= scale["uncertainty"] \
        <= max(r["uncertainty"] for r in scale["ranges"])
    # the SfM points alone would be a worse ruler here: the road motion is what sets the scale
    assert scale["by_height"] != scale["by_road_points"]


def test_the_stored_frames_are_the_clip_undistorted(freeway_build):
    """Frame 40 as stored is the video's frame 40 undistorted by the calibration (JPEG aside),
    and far from the distorted frame towards the corners."""
    from paradrive.ingest.undistort import undistort_image
    from paradrive.scene import read_image
    from paradrive.video import decode_frames

    scene, scene_dir = scene_of(freeway_build)
    intr = scene["video"]["intrinsics"]
    K = np.array([[intr["fx"], 0, intr["cx"]], [0, intr["fy"], intr["cy"]], [0, 0, 1]])
    raw = decode_frames(FREEWAY_VIDEO, [40], seek=False)[0]
    stored = read_image(scene_dir / scene["frames"][40]["cameras"]["front"]["image"]).astype(float)
    undistorted = undistort_image(raw, K, intr["distortion"]).astype(float)
    assert np.abs(stored - undistorted).mean() < 3
    corner = (slice(0, 180), slice(0, 320))
    assert np.abs(stored[corner] - raw[corner]).mean() > 4 * np.abs(stored[corner] - undistorted[corner]).mean()


def test_a_smoke_build_of_the_clip_publishes_pairs(freeway_build):
    report = freeway_build["report"]
    assert not report.failures()
    index = json.loads((freeway_build["build_dir"] / "index.json").read_text())
    assert index["totals"]["scenes"] == 1 and index["totals"]["rows"] > 0
    (scene,) = index["scenes"]
    assert scene["dataset"] == "video" and scene["rows"] == index["totals"]["rows"]


# -- the masks ---------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def freeway_scene(freeway_build) -> Path:
    """The real freeway clip's scene in the session's build of it (its default ingest: every
    frame at 1280x720, undistorted by its calibration)."""
    (scene_dir,) = (freeway_build["data_dir"] / "scenes").iterdir()
    return scene_dir


def test_the_real_clip_s_cars_are_masked_and_its_road_is_not(freeway_scene):
    """Hand-labelled boxes of the two cars ahead on eleven frames (tests/udacity_freeway_cars.json)
    against the moving masks of the real freeway clip; docs/scene-layout.md ("Masks") has the
    figures."""
    from paradrive.ingest.videomasks import labelled_scores

    scores = labelled_scores(freeway_scene, LABELS, FREEWAY / "calibration.json")
    assert len(scores.frames) == 11
    assert scores.coverage >= 0.9 and min(scores.named.values()) >= 0.9, scores.named
    assert scores.road_masked <= 0.05 and scores.worst_road_masked <= 0.05, scores.frames


def test_the_real_clip_s_hood_is_its_ego_mask_and_nothing_above_it(freeway_scene):
    scene = json.loads((freeway_scene / "scene.json").read_text())
    ego = read_image(SceneLayout(freeway_scene).ego_mask("front"))[..., 0] > 127
    h = ego.shape[0]
    assert ego[int(0.97 * h):].all()   # the hood, across the whole width
    assert not ego[:int(0.85 * h)].any()   # no overlay found in the scenery or on the cars
    masks = scene["video"]["masks"]
    assert masks["ego_share"] == pytest.approx(ego.mean(), abs=1e-4) and masks["ego_share"] < 0.1
