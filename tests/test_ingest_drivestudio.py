"""DriveStudio processed folders (Waymo and nuScenes flavours) read back with the known answers."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from conftest import stage_params

from paradrive import geometry
from paradrive.errors import SceneError
from paradrive.ingest import export
from paradrive.stages.ingest import ingest
from paradrive.ingest.common import OPENCV_TO_FLU
from paradrive.scene import load_scene
from paradrive.uri import parse_uri
from synthetic_logs import street_log

CAMS = ("front", "front_left", "front_right")
FRAMES = 4
DIST = (-0.08, 0.02, 0.0005, 0.0, 0.0)


@pytest.fixture(scope="module")
def source():
    return street_log(9, FRAMES, 96, 64, CAMS, lidar_seed=7, lidar_points=1500,
                      lidar_extent_m=25)


@pytest.fixture(scope="module")
def waymo_folder(source, tmp_path_factory):
    return export.export_drivestudio(source, tmp_path_factory.mktemp("ds") / "processed" /
                                     "training" / "023", flavour="waymo", distortion=DIST)


@pytest.fixture(scope="module")
def waymo_scene(waymo_folder, tmp_path_factory):
    out = tmp_path_factory.mktemp("scenes") / "drivestudio-023"
    ingest(f"drivestudio:{waymo_folder}", out, stage_params("ingest", {"cameras": list(CAMS), "image_ext": "png"}))
    return load_scene(out)


def test_layout_is_drivestudios(waymo_folder):
    names = {p.relative_to(waymo_folder).as_posix() for p in waymo_folder.rglob("*")}
    assert {"images/000_0.jpg", "images/003_1.jpg", "ego_pose/000.txt", "extrinsics/0.txt",
            "intrinsics/1.txt", "sky_masks/002_0.png", "lidar/001.bin"} <= names
    assert np.loadtxt(waymo_folder / "intrinsics" / "0.txt").shape == (9,)
    assert parse_uri(f"drivestudio:{waymo_folder}").scene_id == "drivestudio-023"


def test_waymo_flavour_poses_and_intrinsics_round_trip(waymo_scene, source):
    for cam in CAMS:
        assert np.abs(waymo_scene.c2w(cam) - source.c2w[cam]).max() < 1e-6
        truth, got = source.cameras[cam], waymo_scene.cameras[cam]
        assert (got.fx, got.fy, got.cx, got.cy, got.width, got.height) == (
            truth.fx, truth.fy, truth.cx, truth.cy, truth.width, truth.height)
    assert np.abs(waymo_scene.ego2world() - source.ego2world).max() < 1e-6
    assert waymo_scene.fps == 10.0
    assert list(waymo_scene.timestamps_us()) == [0, 100_000, 200_000, 300_000]


def test_waymo_flavour_images_are_undistorted(waymo_scene, source):
    for i in range(FRAMES):
        for cam in CAMS:
            err = np.abs(waymo_scene.load_image(i, cam).astype(float) - source.image(i, cam))
            assert err[4:-4, 4:-4].mean() < 6.0


def test_sky_masks_go_to_masks_sky(waymo_scene, source):
    for i in range(FRAMES):
        got = waymo_scene.sky_mask(i, "front")
        truth = source.sky(i, "front")
        assert got is not None and got.shape == truth.shape
        inner = (slice(4, -4), slice(4, -4))
        assert (got[inner] != truth[inner]).mean() < 0.02
    assert (waymo_scene.root / "masks" / "sky" / "front_left" / "000003.png").is_file()


def test_waymo_flavour_lidar_becomes_world_points(waymo_scene, source):
    got = np.load(waymo_scene.root / "lidar" / "000002.npy")
    assert np.abs(got - source.lidar(2)).max() < 1e-3


def test_ten_column_lidar_files_are_read_too(waymo_folder, source, tmp_path):
    folder = tmp_path / "023"
    shutil.copytree(waymo_folder, folder)
    for path in (folder / "lidar").glob("*.bin"):
        rows = np.fromfile(path, dtype=np.float32).reshape(-1, 14)
        np.concatenate([rows[:, :6], rows[:, 10:]], 1).tofile(path)  # no flow columns
    out = tmp_path / "s"
    ingest(f"drivestudio:{folder}", out, stage_params("ingest", {"cameras": ["front"], "sky_masks": False}))
    assert np.abs(np.load(out / "lidar" / "000001.npy") - source.lidar(1)).max() < 1e-3
    assert not (out / "masks" / "sky").exists()


def test_nuscenes_flavour_uses_the_front_camera_as_ego(source, tmp_path):
    folder = export.export_drivestudio(source, tmp_path / "processed_10Hz" / "mini" / "001",
                                       flavour="nuscenes")
    out = tmp_path / "s"
    ingest(f"drivestudio:{folder}", out, stage_params("ingest", {"cameras": list(CAMS), "image_ext": "png"}))
    scene = load_scene(out)
    ego0 = export.GLOBAL @ source.c2w["front"][0] @ geometry.invert(OPENCV_TO_FLU)
    for cam in CAMS:
        truth = geometry.invert(ego0) @ export.GLOBAL @ source.c2w[cam]
        assert np.abs(scene.c2w(cam) - truth).max() < 1e-6
        assert scene.cameras[cam].fx == source.cameras[cam].fx
    # vehicle axes: the ego x axis points along the front camera's optical axis
    assert np.abs(scene.frames[0].ego2world - np.eye(4)).max() < 1e-9
    assert scene.fps == 10.0  # from the processed_10Hz folder name
    world_from_global = geometry.invert(ego0) @ export.GLOBAL
    truth = source.lidar(0) @ world_from_global[:3, :3].T + world_from_global[:3, 3]
    assert np.abs(np.load(out / "lidar" / "000000.npy") - truth).max() < 1e-3


def test_fps_query_overrides(waymo_folder, tmp_path):
    out = tmp_path / "s"
    ingest(f"drivestudio:{waymo_folder}?fps=12", out, stage_params("ingest", {"cameras": ["front"], "max_frames": 2,
                                                        "lidar": False}))
    scene = load_scene(out)
    assert scene.fps == 12.0 and len(scene.frames) == 2


def _copy(folder, tmp_path):
    dst = tmp_path / "023"
    shutil.copytree(folder, dst)
    return dst


def test_missing_image_is_named(waymo_folder, tmp_path):
    folder = _copy(waymo_folder, tmp_path)
    (folder / "images" / "002_1.jpg").unlink()
    with pytest.raises(SceneError, match=r"frame 2 camera front_left image is missing \(.*002_1.jpg\)"):
        ingest(f"drivestudio:{folder}", tmp_path / "s", stage_params("ingest", {"cameras": list(CAMS)}))
    assert not (tmp_path / "s").exists()


def test_camera_without_calibration_is_named(waymo_folder, tmp_path):
    with pytest.raises(SceneError, match=r"calibration missing for camera\(s\) side_left"):
        ingest(f"drivestudio:{waymo_folder}", tmp_path / "s", stage_params("ingest", {"cameras": ["side_left"]}))


def test_nan_ego_pose_is_reported(waymo_folder, tmp_path):
    folder = _copy(waymo_folder, tmp_path)
    pose = np.loadtxt(folder / "ego_pose" / "002.txt")
    pose[0, 3] = np.nan
    np.savetxt(folder / "ego_pose" / "002.txt", pose)
    with pytest.raises(SceneError, match=r"frame 2 ego pose has NaN \(.*ego_pose/002.txt\)"):
        ingest(f"drivestudio:{folder}", tmp_path / "s", stage_params("ingest", {"cameras": ["front"]}))


def test_gap_in_frames_is_reported(waymo_folder, tmp_path):
    folder = _copy(waymo_folder, tmp_path)
    (folder / "ego_pose" / "001.txt").unlink()
    with pytest.raises(SceneError, match=r"frame 001 is missing"):
        ingest(f"drivestudio:{folder}", tmp_path / "s", stage_params("ingest", {"cameras": ["front"]}))


def test_not_a_scene_folder_is_reported(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(SceneError, match="not a DriveStudio scene folder"):
        ingest(f"drivestudio:{tmp_path / 'empty'}", tmp_path / "s", stage_params("ingest", {}))
