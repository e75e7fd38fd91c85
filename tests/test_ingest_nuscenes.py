"""nuScenes v1.0 tables: a synthetic street written as tables + images reads back exactly."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from conftest import stage_params

from paradrive.errors import SceneError
from paradrive.ingest import export
from paradrive.stages.ingest import ingest
from paradrive.scene import load_scene
from paradrive.uri import parse_uri
from synthetic_logs import street_log

CAMS = ("front", "front_left", "front_right")
FRAMES = 7


@pytest.fixture(scope="module")
def source():
    return street_log(5, FRAMES, 80, 48, CAMS, lidar_seed=100, lidar_points=2000,
                      lidar_extent_m=30)


@pytest.fixture(scope="module")
def dataroot(source, tmp_path_factory):
    root = tmp_path_factory.mktemp("nuscenes")
    export.export_nuscenes(source, root, image_format="png", keyframe_every=3,
                           scene_name="scene-0061")
    return root


URI = "nuscenes:{root}?version=v1.0-mini#scene-0061"


@pytest.fixture(scope="module")
def scene(dataroot, tmp_path_factory):
    out = tmp_path_factory.mktemp("scenes") / "nuscenes-scene-0061"
    ingest(URI.format(root=dataroot), out, stage_params("ingest", {"cameras": list(CAMS), "image_ext": "png"}))
    return load_scene(out)


def test_scene_id_is_the_scene_name(dataroot):
    assert parse_uri(URI.format(root=dataroot)).scene_id == "nuscenes-scene-0061"


def test_tables_have_the_v1_schema(dataroot):
    meta = dataroot / "v1.0-mini"
    sd = json.loads((meta / "sample_data.json").read_text())[0]
    assert set(sd) >= {"token", "sample_token", "ego_pose_token", "calibrated_sensor_token",
                       "timestamp", "fileformat", "is_key_frame", "height", "width", "filename",
                       "prev", "next"}
    cs = json.loads((meta / "calibrated_sensor.json").read_text())[0]
    assert set(cs) == {"token", "sensor_token", "translation", "rotation", "camera_intrinsic"}
    assert {s["channel"] for s in json.loads((meta / "sensor.json").read_text())} == {
        "CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT", "LIDAR_TOP"}


def test_keyframes_and_sweeps_are_all_frames(scene, source):
    assert len(scene.frames) == FRAMES  # 3 keyframes + 4 sweeps
    assert np.array_equal(scene.timestamps_us() - scene.timestamps_us()[0],
                          source.timestamps_us - source.timestamps_us[0])
    assert math.isclose(scene.fps, source.fps)


def test_poses_and_intrinsics_round_trip_exactly(scene, source):
    for cam in CAMS:
        assert np.abs(scene.c2w(cam) - source.c2w[cam]).max() < 1e-6
        truth, got = source.cameras[cam], scene.cameras[cam]
        assert (got.fx, got.fy, got.cx, got.cy, got.width, got.height) == (
            truth.fx, truth.fy, truth.cx, truth.cy, truth.width, truth.height)
    assert np.abs(scene.ego2world() - source.ego2world).max() < 1e-6


def test_png_images_are_exact(scene, source):
    for i in range(FRAMES):
        for cam in CAMS:
            assert np.array_equal(scene.load_image(i, cam), source.image(i, cam))


def test_lidar_sweeps_become_world_points(scene, source):
    for i in (0, FRAMES - 1):
        got = np.load(scene.root / "lidar" / f"{i:06d}.npy")
        assert np.abs(got - source.lidar(i)).max() < 1e-3  # float32 on disk


def test_jpeg_log_images_are_copied_as_they_are(source, tmp_path):
    root = tmp_path / "nus"
    export.export_nuscenes(source, root, cameras=["front"], frames=3, image_format="jpg",
                           lidar=False, scene_name="scene-0061")
    out = tmp_path / "s"
    ingest(URI.format(root=root), out, stage_params("ingest", {"cameras": ["front"]}))
    scene = load_scene(out)
    rows = json.loads((root / "v1.0-mini" / "sample_data.json").read_text())
    first = next(r for r in rows if r["prev"] == "" and "CAM_FRONT" in r["filename"])
    assert (out / scene.frames[0].cameras["front"].image).read_bytes() == (
        root / first["filename"]).read_bytes()
    assert np.abs(scene.load_image(1, "front").astype(float) - source.image(1, "front")).mean() < 3.0


def _copy(dataroot, tmp_path):
    import shutil

    root = tmp_path / "nus"
    shutil.copytree(dataroot, root)
    return root


def _edit(root, table, fn):
    path = root / "v1.0-mini" / f"{table}.json"
    rows = json.loads(path.read_text())
    fn(rows)
    path.write_text(json.dumps(rows))


def test_missing_table_is_named(dataroot, tmp_path):
    root = _copy(dataroot, tmp_path)
    (root / "v1.0-mini" / "sample_data.json").unlink()
    with pytest.raises(SceneError, match=r"table sample_data.json is missing \(.*v1.0-mini/sample_data.json\); "):
        ingest(URI.format(root=root), tmp_path / "s", stage_params("ingest", {"cameras": ["front"]}))
    assert not (tmp_path / "s").exists()


def test_missing_sweep_image_is_named(dataroot, tmp_path):
    root = _copy(dataroot, tmp_path)
    victim = next((root / "sweeps" / "CAM_FRONT").iterdir())
    victim.unlink()
    with pytest.raises(SceneError, match=r"image of sample_data \w+ \(front, frame \d\) is missing"):
        ingest(URI.format(root=root), tmp_path / "s", stage_params("ingest", {"cameras": ["front"]}))


def test_camera_without_calibration_is_named(dataroot, tmp_path):
    with pytest.raises(SceneError, match=r"calibration missing for camera\(s\) back"):
        ingest(URI.format(root=dataroot), tmp_path / "s", stage_params("ingest", {"cameras": ["front", "back"]}))


def test_non_monotonic_timestamps_are_reported(dataroot, tmp_path):
    root = _copy(dataroot, tmp_path)
    rows = json.loads((root / "v1.0-mini" / "sample_data.json").read_text())
    front = [r for r in rows if "/CAM_FRONT/" in r["filename"]]
    stamp = min(r["timestamp"] for r in front)

    third = sorted(front, key=lambda x: x["timestamp"])[2]["token"]

    def rewind(rows):
        for r in rows:
            if r["token"] == third:
                r["timestamp"] = stamp
    _edit(root, "sample_data", rewind)
    with pytest.raises(SceneError, match=r"\(frame 2, front\) timestamp \d+ us is not after "
                                         r".*\(non-monotonic timestamps\)"):
        ingest(URI.format(root=root), tmp_path / "s", stage_params("ingest", {"cameras": ["front"]}))


def test_nan_ego_pose_is_reported(dataroot, tmp_path):
    root = _copy(dataroot, tmp_path)

    def poison(rows):
        rows[4]["translation"][1] = float("nan")
    _edit(root, "ego_pose", poison)
    with pytest.raises(SceneError, match=r"ego_pose \w+ has NaN \(.*ego_pose.json\); fix or drop"):
        ingest(URI.format(root=root), tmp_path / "s", stage_params("ingest", {"cameras": ["front"], "lidar": False}))


def test_unknown_scene_name_is_reported(dataroot, tmp_path):
    with pytest.raises(SceneError, match=r"no scene 'scene-9999'"):
        ingest(f"nuscenes:{dataroot}?version=v1.0-mini#scene-9999", tmp_path / "s", stage_params("ingest", {}))


# -- a row without a key the reader uses -------------------------------------------------------

def _read_rows(root, table):
    return json.loads((root / "v1.0-mini" / f"{table}.json").read_text())


def _victim(root, table, channel="CAM_FRONT"):
    """The token of the row of ``table`` the reader reads first for ``channel``: the scene, its
    first sample, the camera's first sample_data and that row's ego pose, calibration, sensor."""
    (scene,) = _read_rows(root, "scene")
    sd = next(r for r in _read_rows(root, "sample_data")
              if r["prev"] == "" and f"/{channel}/" in r["filename"])
    cs = next(r for r in _read_rows(root, "calibrated_sensor") if r["token"] == sd["calibrated_sensor_token"])
    return {"scene": scene["token"], "sample": scene["first_sample_token"], "sample_data": sd["token"],
            "ego_pose": sd["ego_pose_token"], "calibrated_sensor": cs["token"],
            "sensor": cs["sensor_token"]}[table]


def _without(root, table, key, channel="CAM_FRONT"):
    """``root``'s ``table`` with ``key`` taken out of the row the reader reads first; its token."""
    token = _victim(root, table, channel)
    _edit(root, table, lambda rows: next(r for r in rows if r["token"] == token).pop(key))
    return token


def _missing_key_message(root, table, token, key):
    return (f"scene nuscenes-scene-0061: {table}.json row {token!r} has no key {key!r} "
            f"({root / 'v1.0-mini' / f'{table}.json'}); the table is incomplete or damaged: "
            f"re-extract the nuScenes metadata archive")


@pytest.mark.parametrize("table, key, channel", [
    ("sample_data", "filename", "CAM_FRONT"), ("sample_data", "timestamp", "CAM_FRONT"),
    ("sample_data", "ego_pose_token", "CAM_FRONT"), ("sample_data", "calibrated_sensor_token", "CAM_FRONT"),
    ("sample_data", "filename", "LIDAR_TOP"), ("scene", "first_sample_token", "CAM_FRONT"),
    ("sample", "timestamp", "CAM_FRONT"), ("ego_pose", "rotation", "CAM_FRONT"),
    ("calibrated_sensor", "sensor_token", "CAM_FRONT"), ("calibrated_sensor", "translation", "CAM_FRONT"),
    ("sensor", "channel", "CAM_FRONT"),
])
def test_a_row_without_a_key_the_reader_uses_fails_the_scene_naming_table_row_and_key(
        dataroot, tmp_path, table, key, channel):
    from paradrive.pipeline import StageRegistry, run_build

    root = _copy(dataroot, tmp_path)
    token = _without(root, table, key, channel)
    config = StageRegistry().resolve("smoke", {"ingest": {"cameras": ["front"], "image_ext": "png",
                                                          "lidar": True}})
    report = run_build(config, [URI.format(root=root)], tmp_path / "data", stages=["ingest"],
                       manifests_dir=tmp_path / "m", build="b")
    (failure,) = report.failures()   # failed with the reason, not crashed
    assert (failure.stage, failure.status) == ("ingest", "failed")
    assert failure.error == _missing_key_message(root, table, token, key)
    assert list((tmp_path / "data" / "scenes").iterdir()) == []


def test_a_row_without_a_key_is_named_when_the_tables_are_read_whole(dataroot, tmp_path):
    from paradrive.ingest import nuscenes
    from paradrive.ingest.nuscenes_tables import JsonTables

    root = _copy(dataroot, tmp_path)
    token = _without(root, "sample_data", "filename")
    uri = parse_uri(URI.format(root=root))
    with pytest.raises(SceneError) as err:
        nuscenes.read(uri, tmp_path / "s", stage_params("ingest", {"cameras": ["front"], "image_ext": "png"}),
                      uri.scene_id, JsonTables.load(root / "v1.0-mini", uri.scene_id))
    assert str(err.value) == _missing_key_message(root, "sample_data", token, "filename")
