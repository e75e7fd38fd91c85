"""The video: input on a real KITTI odometry snippet (../shared/realdata/kitti-odometry-snippet:
51 grey frames at 1241x376 and 10 Hz on a curving on-ramp, GPS/INS poses, the camera 1.65 m
above the road), from its frames alone, without its intrinsics: the focal length found within
5 % of the calibrated 718.856 px, every frame registered, the path within 3 % of the GPS/INS
path and within two of the scale's stated uncertainties, and the trajectory within 1 % of the
path after a rigid alignment. One ingest for the module (about two minutes on two cores).
And its GPS/INS poses written as a one-camera DriveStudio folder (what the held-out comparison
fits on) read back as they are. Skipped where the snippet is not there."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import REALDATA, load_bench, read_only

pytestmark = pytest.mark.slow

KITTI = REALDATA / "kitti-odometry-snippet"
FX = 718.856
HEIGHT_M = 1.65


def truth_centres() -> np.ndarray:
    """(51, 3) the GPS/INS camera centres (poses.txt: a 3x4 camera-to-world matrix a line)."""
    return np.loadtxt(KITTI / "poses.txt").reshape(-1, 3, 4)[:, :, 3]


def path(centres: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(centres, axis=0), axis=1).sum())


def rigid_ate(found: np.ndarray, truth: np.ndarray) -> float:
    """RMS distance between ``found`` and ``truth`` centres (N, 3) after the rotation and
    translation that fit them best (Kabsch; no scale: the scale's error counts)."""
    a, b = found - found.mean(0), truth - truth.mean(0)
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))])
    rotation = vt.T @ d @ u.T
    return float(np.sqrt(((a @ rotation.T - b) ** 2).sum(1).mean()))


@pytest.fixture(scope="module")
def kitti_scene(tmp_path_factory):
    """The snippet's frames ingested as ``video:<folder>?height_m=1.65`` (10 Hz, the folder
    default): no fx=, no fov_deg=."""
    if not (KITTI / "image_l").is_dir():
        pytest.skip(f"the KITTI snippet is not here ({KITTI}): a clone without ../shared/realdata")
    from paradrive.scene import load_scene
    from paradrive.stages.ingest import ingest, params_of

    root = tmp_path_factory.mktemp("kitti") / "video-image_l"
    summary = ingest(f"video:{KITTI / 'image_l'}?height_m={HEIGHT_M}", root, params_of())
    yield from read_only(root, (load_scene(root), summary))


def test_the_focal_length_is_found_from_the_frames(kitti_scene):
    scene, summary = kitti_scene
    intr = summary["video"]["intrinsics"]
    assert intr["estimated"] and intr["given_by"] == "focal search"
    search = intr["focal_search"]
    assert search["observable"] and search["rise"] > 0.1
    assert intr["fx"] == pytest.approx(FX, rel=0.05)
    assert scene.cameras["front"].fx == intr["fx"]
    # the focal's uncertainty is part of the scale's
    assert summary["video"]["scale"]["parts"]["focal"] == pytest.approx(search["uncertainty"])


def test_every_frame_registers(kitti_scene):
    scene, summary = kitti_scene
    assert summary["video"]["registered"] == "0-50" and len(scene.frames) == 51
    assert scene.fps == pytest.approx(10.0)


def test_the_path_is_the_gps_ins_path_within_its_stated_uncertainty(kitti_scene):
    scene, summary = kitti_scene
    scale = summary["video"]["scale"]
    error = path(scene.c2w("front")[:, :3, 3]) / path(truth_centres()) - 1
    assert abs(error) < 0.03, error
    assert abs(error) <= 2 * scale["uncertainty"], (error, scale["uncertainty"])
    assert scale["uncertainty"] <= 0.05
    # each half of the frames was measured, by the cues that could: the road's motion does not
    # align on the sharp first half of the bend, the road points carry it
    first, second = scale["ranges"]
    assert (first["frames"], second["frames"]) == ([0, 25], [26, 50])
    assert first["carried_by"] == ["road points"] and "road points" in second["carried_by"]
    (motion,) = [c for c in first["cues"] if c["cue"] == "road motion"]
    assert not motion["measured"] and "frame pairs aligned" in motion["why"]


def test_the_trajectory_keeps_its_shape(kitti_scene):
    """Within 1 % of the path after a rigid alignment: the scale per range takes out SfM's drift
    (12 % between the ends of this bend), which one scale for the whole path leaves in."""
    scene, summary = kitti_scene
    found, truth = scene.c2w("front")[:, :3, 3], truth_centres()
    assert rigid_ate(found, truth) < 0.01 * path(truth)
    assert summary["video"]["scale"]["parts"]["between_ranges"] > 0.03


def test_the_gps_ins_poses_as_a_one_camera_drivestudio_folder_ingest_as_they_are(tmp_path, caplog):
    """The folder the held-out comparison fits on (``bench_video.py --parts kitti_heldout``):
    one camera, no LiDAR, read under ``ingest.cameras: auto`` (the Waymo set's other cameras are
    named as left out), its camera poses KITTI's GPS/INS poses and its camera the rectified one."""
    if not (KITTI / "image_l").is_dir():
        pytest.skip(f"the KITTI snippet is not here ({KITTI}): a clone without ../shared/realdata")
    from paradrive.scene import load_scene
    from paradrive.stages.ingest import ingest, params_of

    bench = load_bench("bench_video")
    uri = bench.kitti_drivestudio(KITTI, tmp_path / "folder")
    with caplog.at_level("WARNING", logger="paradrive.ingest"):
        summary = ingest(uri, tmp_path / "scene", params_of())
    assert summary["cameras"] == ["front"]
    assert "the log has no front_left, front_right, so the fit sees front" in caplog.text
    scene = load_scene(tmp_path / "scene")
    camera = scene.cameras["front"]
    assert (camera.width, camera.height, camera.fx, camera.fy) == (1241, 376, FX, FX)
    c2w = scene.c2w("front")
    relative = np.linalg.inv(c2w[0]) @ c2w          # in the first camera's frame, as poses.txt
    np.testing.assert_allclose(relative[:, :3, 3], truth_centres(), atol=1e-5)
    # the world is level with the first camera, the ego frame on the road under it
    assert scene.frames[0].ego2world[2, 3] == pytest.approx(0.0) and c2w[0, 2, 3] == pytest.approx(HEIGHT_M)
    assert not (tmp_path / "scene" / "lidar").exists() or not any((tmp_path / "scene" / "lidar").iterdir())
