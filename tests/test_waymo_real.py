"""One REAL Waymo Open Dataset v1 frame through the Waymo reader: five cameras with their
calibrations (intrinsics and distortion), a camera rig with plausible poses, the laser labels as
actors, and a build of the one-frame segment refused as too short for a clip before any fit.

The frame is read from ``../shared/realdata/waymo-v1-one-frame/`` beside the repository (never
copied into it); the tests skip where that folder is absent."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from conftest import stage_params
from paradrive.ingest import waymo
from paradrive.ingest.common import decode_jpeg
from paradrive.ingest.undistort import undistort_image
from paradrive.scene import read_image
from paradrive.uri import parse_uri

FOLDER = Path(__file__).resolve().parents[1].parent / "shared" / "realdata" / "waymo-v1-one-frame"
SEGMENT = FOLDER / "segment-1024360143612057520_3580_000_3600_000_with_camera_labels.tfrecord"
SCENE_ID = "waymo-1024360143612057520_3580_000_3600_000"
pytestmark = pytest.mark.skipif(not SEGMENT.is_file(),
                                reason=f"the real Waymo frame is not here: {FOLDER} (../shared/realdata/"
                                       f"waymo-v1-one-frame beside the repository)")

# the rig of Waymo's vehicles: camera -> where it looks (degrees left of forward) and image size
RIG = {"front": (0, 1920, 1280), "front_left": (45, 1920, 1280), "front_right": (-45, 1920, 1280),
       "side_left": (90, 1920, 886), "side_right": (-90, 1920, 886)}


@pytest.fixture(scope="module")
def frame():
    """The segment's one record, decoded."""
    records = list(waymo.iter_frames(SEGMENT, SCENE_ID))
    assert [index for index, _ in records] == [0]
    return records[0][1]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """The segment read with every camera (ingest.cameras: null): the scene and its folder."""
    out = tmp_path_factory.mktemp("waymo-real")
    uri = parse_uri(f"waymo:{SEGMENT}")
    assert uri.scene_id == SCENE_ID
    return waymo.read(uri, out, stage_params("ingest", {"cameras": None}), SCENE_ID), out


def test_the_frame_has_five_cameras_with_intrinsics_and_distortion(frame):
    calibrations = {waymo.camera_name(c.name): c for c in frame.context.camera_calibrations}
    assert set(calibrations) == set(RIG)
    assert {waymo.camera_name(im.name) for im in frame.images} == set(RIG)
    for name, calib in calibrations.items():
        _, width, height = RIG[name]
        assert (calib.width, calib.height) == (width, height)
        fu, fv, cu, cv, *dist = calib.intrinsic
        assert len(dist) == 5   # k1, k2, p1, p2, k3
        # about 50 degrees across 1920 pixels; the principal point near the sensor's centre,
        # which the side cameras' images (the top 886 of the sensor's 1280 rows) hold 394 rows up
        assert 1900 < fu < 2200 and abs(fu - fv) < 1e-6 * fu
        assert abs(cu - width / 2) < 0.05 * width and abs(cv - (1280 / 2 - (1280 - height))) < 0.05 * 1280
        k1, k2, p1, p2, k3 = dist
        assert abs(k1) < 0.1 and -0.5 < k2 < -0.1 and abs(p1) < 0.01 and abs(p2) < 0.01 and k3 == 0


def test_every_camera_is_read_at_its_calibration_and_stored_undistorted(frame, scene):
    scene_, out = scene
    assert list(scene_.cameras) == ["front", "front_left", "front_right", "side_left", "side_right"]
    assert len(scene_.frames) == 1 and scene_.fps == waymo.FPS
    calibrations = {waymo.camera_name(c.name): c for c in frame.context.camera_calibrations}
    images = {waymo.camera_name(im.name): im.image for im in frame.images}
    for name, camera in scene_.cameras.items():
        calib = calibrations[name]
        assert (camera.width, camera.height) == (calib.width, calib.height)
        assert [camera.fx, camera.fy, camera.cx, camera.cy] == list(calib.intrinsic[:4])
        stored = read_image(out / scene_.frames[0].cameras[name].image).astype(np.float64)
        raw = decode_jpeg(images[name], scene_id=SCENE_ID, where=name)
        undistorted = undistort_image(raw, camera.K(), list(calib.intrinsic[4:9]))
        # the stored image is the recorded one undistorted (up to its JPEG encoding), not as recorded
        assert np.abs(stored - undistorted).mean() < 1.5
        assert np.abs(stored - raw).mean() > 2.5


def test_the_camera_rig_has_the_poses_of_a_real_car(scene):
    scene_, _ = scene
    frame = scene_.frames[0]
    np.testing.assert_allclose(frame.ego2world, np.eye(4), atol=1e-9)   # world = the first vehicle pose
    for name, (yaw, _, _) in RIG.items():
        c2w = frame.cameras[name].c2w
        np.testing.assert_allclose(c2w[:3, :3] @ c2w[:3, :3].T, np.eye(3), atol=1e-6)
        assert np.linalg.det(c2w[:3, :3]) > 0
        looks = c2w[:3, 2]   # OpenCV +z, the viewing direction, in the vehicle frame (x forward, y left)
        assert abs(np.degrees(np.arctan2(looks[1], looks[0])) - yaw) < 5, name
        assert abs(np.degrees(np.arcsin(looks[2]))) < 5, name           # level
        assert (c2w[:3, 1] @ [0, 0, 1]) < -0.99, name                   # image down is world down
        x, y, z = c2w[:3, 3]   # on the roof, ahead of the rear axle, near the car's centre line
        assert 1.0 < x < 2.5 and abs(y) < 0.5 and 1.8 < z < 2.5, name
        rig = frame.ego2world @ scene_.cameras[name].cam2ego   # the image was taken at the frame's pose
        np.testing.assert_allclose(c2w[:3, 3], rig[:3, 3], atol=0.05)


def test_the_laser_labels_become_actors_of_plausible_class_and_size(frame, scene):
    scene_, _ = scene
    labels = list(frame.laser_labels)
    assert len(labels) == 75 and Counter(label.type for label in labels) == {1: 37, 3: 25, 2: 12, 4: 1}
    # signs (type 3) are not actors; every vehicle, pedestrian and cyclist is one
    assert Counter(a.cls for a in scene_.actors) == {"vehicle": 37, "pedestrian": 12, "cyclist": 1}
    assert {a.id for a in scene_.actors} == {f"waymo:{label.id}" for label in labels if label.type != 3}
    sizes = {"vehicle": ((3.5, 20), (1.0, 4.5), (1.2, 4.5)), "pedestrian": ((0.3, 1.5), (0.3, 1.2), (1.0, 2.3)),
             "cyclist": ((1.2, 2.5), (0.4, 1.2), (1.2, 2.2))}
    by_id = {f"waymo:{label.id}": label for label in labels}
    for actor in scene_.actors:
        assert actor.frames.tolist() == [0] and actor.rigid == (actor.cls == "vehicle")
        for value, (low, high) in zip(actor.size, sizes[actor.cls]):
            assert low <= value <= high, (actor.id, actor.cls, actor.size)
        box = by_id[actor.id].box
        centre = actor.box2world[0][:3, 3]
        np.testing.assert_allclose(centre, [box.center_x, box.center_y, box.center_z], atol=1e-6)
        assert np.hypot(*centre[:2]) < 80 and -3 < centre[2] < 6   # within the laser's reach, near the road


def test_a_build_of_the_one_frame_segment_is_refused_as_too_short_before_any_fit(tmp_path):
    from typer.testing import CliRunner

    from paradrive.cli import app

    result = CliRunner().invoke(app, ["build", "--scene", f"waymo:{SEGMENT}", "--profile", "smoke",
                                      "--data", str(tmp_path / "data"), "--manifests", str(tmp_path / "m"),
                                      "--build", "real"], env={"COLUMNS": "500"})
    assert result.exit_code == 1, result.output
    scene_dir = tmp_path / "data" / "scenes" / SCENE_ID
    lines = [line.strip() for line in result.output.splitlines()]
    assert (f"failed fit      {SCENE_ID} — scene {SCENE_ID}: it has 1 frame, and a clip needs 9 "
            f"(render.clip_frames) ({scene_dir / 'scene.json'}); set a shorter render.clip_frames (at "
            f"most 1) or use another scene") in lines
    assert f"blocked render   {SCENE_ID} — not run: fit failed" in lines
    assert (scene_dir / "scene.json").is_file() and not (scene_dir / "gs").exists()   # no fit began
