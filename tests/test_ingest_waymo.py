"""Waymo segments: a synthetic street written as a real TFRecord of Frame protos reads back exactly."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest

from conftest import stage_params

from paradrive import geometry
from paradrive.errors import SceneError
from paradrive.ingest import export
from paradrive.stages.ingest import ingest
from paradrive.ingest import undistort as ud
from paradrive.ingest import waymo
from paradrive.scene import load_scene
from paradrive.uri import parse_uri

CAMS = ("front", "front_left", "front_right")
DIST = {"front": (-0.12, 0.03, 0.0008, -0.0006, 0.002)}
SEGMENT = "segment-1234_with_camera_labels.tfrecord"


def fake_lidar(i: int, ego2world: np.ndarray) -> np.ndarray:
    """World points on walls and ground around the ego (cheap stand-in for the ray-cast LiDAR)."""
    rng = np.random.default_rng(i)
    az = rng.uniform(-np.pi, np.pi, 3000)
    dist = rng.uniform(4.0, 40.0, 3000)
    z = rng.uniform(-1.9, 2.0, 3000)
    local = np.stack([dist * np.cos(az), dist * np.sin(az), z], 1)
    return local @ ego2world[i][:3, :3].T + ego2world[i][:3, 3]


@pytest.fixture(scope="module")
def source():
    from paradrive.synthetic import SyntheticStreet

    street = SyntheticStreet("demo", seed=3, frames=4, width=96, height=64, cameras=CAMS)
    src = export.source_from_street(street)
    return dataclasses.replace(src, lidar=lambda i: fake_lidar(i, src.ego2world))


@pytest.fixture(scope="module")
def segment(source, tmp_path_factory):
    path = tmp_path_factory.mktemp("waymo") / SEGMENT
    export.export_waymo(source, path, distortion=DIST)
    return path


@pytest.fixture(scope="module")
def ingested(segment, tmp_path_factory):
    out = tmp_path_factory.mktemp("scenes") / "waymo-1234"
    summary = ingest(f"waymo:{segment}", out, stage_params("ingest", {"cameras": list(CAMS), "image_ext": "png"}))
    return summary, load_scene(out)


def test_scene_id_drops_segment_prefix_and_suffix(segment):
    assert parse_uri(f"waymo:{segment}").scene_id == "waymo-1234"


def test_poses_and_intrinsics_round_trip_exactly(source, ingested):
    summary, scene = ingested
    assert summary == {"frames": 4, "cameras": sorted(CAMS), "dataset": "waymo"}
    for cam in CAMS:
        assert np.abs(scene.c2w(cam) - source.c2w[cam]).max() < 1e-6
        truth, got = source.cameras[cam], scene.cameras[cam]
        assert (got.fx, got.fy, got.cx, got.cy, got.width, got.height) == (
            truth.fx, truth.fy, truth.cx, truth.cy, truth.width, truth.height)
        assert np.abs(got.cam2ego - truth.cam2ego).max() < 1e-9
    assert np.abs(scene.ego2world() - source.ego2world).max() < 1e-6
    assert np.array_equal(scene.timestamps_us(), source.timestamps_us)
    assert scene.fps == 10.0 and scene.dataset == "waymo"


def test_world_is_the_first_vehicle_pose(ingested):
    _, scene = ingested
    assert np.abs(scene.frames[0].ego2world - np.eye(4)).max() < 1e-9


def test_images_match_after_jpeg_and_undistortion(source, ingested):
    _, scene = ingested
    for i in range(4):
        plain = scene.load_image(i, "front_left").astype(float)
        assert np.abs(plain - source.image(i, "front_left")).mean() < 3.0  # JPEG only
        undistorted = scene.load_image(i, "front").astype(float)
        err = np.abs(undistorted - source.image(i, "front"))
        assert err[4:-4, 4:-4].mean() < 6.0  # JPEG + distort + undistort resampling
        # without undistortion the distorted image is clearly further from the truth
        raw = ud.distort_image(source.image(i, "front"), source.cameras["front"].K(), DIST["front"])
        assert np.abs(raw.astype(float) - source.image(i, "front"))[4:-4, 4:-4].mean() > err[4:-4, 4:-4].mean()


def test_top_lidar_range_image_becomes_world_points(source, ingested):
    _, scene = ingested
    for i in (0, 3):
        got = np.load(scene.root / "lidar" / f"{i:06d}.npy").astype(np.float64)
        truth = source.lidar(i)
        assert len(got) > 0.8 * len(truth)
        sensor = source.ego2world[i][:3, 3] + source.ego2world[i][:3, :3] @ source.lidar_origin
        d = np.sqrt(((got[::10, None, :] - truth[None, :, :]) ** 2).sum(-1)).min(1)
        rng = np.linalg.norm(got[::10] - sensor, axis=1)
        # binning error: half a row (0.25 deg) and half a column (pi / 2048) at the point's range
        assert np.all(d <= rng * 0.006 + 1e-3)


def test_jpeg_images_are_copied_without_reencoding(segment, tmp_path):
    out = tmp_path / "waymo-1234"
    ingest(f"waymo:{segment}", out,
           stage_params("ingest", {"cameras": ["front_left"], "max_frames": 2, "lidar": False}))
    scene = load_scene(out)
    frame = next(f for _, f in waymo.iter_frames(segment, "x"))
    original = next(bytes(im.image) for im in frame.images if im.name == 2)
    assert (out / scene.frames[0].cameras["front_left"].image).read_bytes() == original
    assert len(scene.frames) == 2 and not (out / "lidar").exists()


def test_folder_lists_segments_and_fragment_picks_one(segment, tmp_path):
    folder = tmp_path / "logs"
    folder.mkdir()
    shutil.copy(segment, folder / SEGMENT)
    shutil.copy(segment, folder / "segment-999_with_camera_labels.tfrecord")
    (folder / "notes.txt").write_text("not a segment")
    uris = waymo.list_segments(folder)
    assert uris == [f"waymo:{folder / SEGMENT}",
                    f"waymo:{folder / 'segment-999_with_camera_labels.tfrecord'}"]
    assert waymo.resolve_segment(parse_uri(f"waymo:{folder}#999"), "x").name.startswith("segment-999")
    with pytest.raises(SceneError, match="folder holds 2 segments"):
        waymo.resolve_segment(parse_uri(f"waymo:{folder}"), "x")
    with pytest.raises(SceneError, match="no segment '777'"):
        waymo.resolve_segment(parse_uri(f"waymo:{folder}#777"), "x")


def test_camera_missing_from_the_log_is_named(segment, tmp_path):
    with pytest.raises(SceneError, match=r"calibration missing for camera\(s\) side_left"):
        ingest(f"waymo:{segment}", tmp_path / "s", stage_params("ingest", {"cameras": ["front", "side_left"]}))
    assert not (tmp_path / "s").exists()


def test_crc_mismatch_names_segment_and_record(segment, tmp_path):
    bad = tmp_path / SEGMENT
    raw = bytearray(segment.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    bad.write_bytes(bytes(raw))
    with pytest.raises(SceneError) as err:
        ingest(f"waymo:{bad}", tmp_path / "s", stage_params("ingest", {"cameras": ["front"]}))
    text = str(err.value)
    assert "scene waymo-1234" in text or "scene s" in text
    assert "CRC mismatch" in text and "record" in text and str(bad) in text and "re-download" in text
    assert not (tmp_path / "s").exists()


def test_truncated_segment_is_reported(segment, tmp_path):
    bad = tmp_path / SEGMENT
    bad.write_bytes(segment.read_bytes()[:-1000])
    with pytest.raises(SceneError, match=r"record 3 .*truncated record"):
        ingest(f"waymo:{bad}", tmp_path / "s", stage_params("ingest", {"cameras": ["front"]}))


def _log(source, **changes):
    """A copy of the source with some truth replaced (bad logs are written from it)."""
    return dataclasses.replace(source, **changes)


def test_non_monotonic_timestamps_are_reported(source, tmp_path):
    stamps = source.timestamps_us.copy()
    stamps[2] = stamps[1]
    path = tmp_path / "seg.tfrecord"
    export.export_waymo(_log(source, timestamps_us=stamps), path, lidar=False)
    with pytest.raises(SceneError, match=r"frame 2 timestamp 100000 us is not after .*non-monotonic.*record 2"):
        ingest(f"waymo:{path}", tmp_path / "s", stage_params("ingest", {"cameras": ["front"]}))


def test_nan_vehicle_pose_is_reported(source, tmp_path):
    ego = source.ego2world.copy()
    ego[1, 0, 3] = np.nan
    path = tmp_path / "seg.tfrecord"
    export.export_waymo(_log(source, ego2world=ego), path, lidar=False)
    with pytest.raises(SceneError, match=r"frame 1 vehicle pose has NaN \(.*seg.tfrecord record 1\); fix or drop"):
        ingest(f"waymo:{path}", tmp_path / "s", stage_params("ingest", {"cameras": ["front"]}))


def test_image_pose_is_used_not_the_frame_pose(source, tmp_path):
    # rolling shutter: images taken 20 ms after the frame's pose, while the car moves
    shifted = {c: geometry.translation(x=0.16) @ p for c, p in source.c2w.items()}
    path = tmp_path / "seg.tfrecord"
    export.export_waymo(_log(source, c2w=shifted), path, lidar=False)
    out = tmp_path / "s"
    ingest(f"waymo:{path}", out, stage_params("ingest", {"cameras": ["front"], "image_ext": "png"}))
    scene = load_scene(out)
    assert np.abs(scene.c2w("front") - shifted["front"]).max() < 1e-6
    assert np.abs(scene.ego2world() - source.ego2world).max() < 1e-6


def test_undistortion_inverts_distortion_and_keeps_the_pinhole_centre():
    dist = (-0.3, 0.1, 0.001, -0.002, -0.02)
    x, y = np.meshgrid(np.linspace(-0.6, 0.6, 21), np.linspace(-0.4, 0.4, 15))
    xd, yd = ud.distort_normalized(x, y, dist)
    xu, yu = ud.undistort_normalized(xd, yd, dist)
    assert np.abs(xu - x).max() < 1e-9 and np.abs(yu - y).max() < 1e-9
    # a smooth image survives distort -> undistort up to interpolation
    h, w = 60, 90
    v, u = np.mgrid[0:h, 0:w]
    img = np.stack([u * 2.5, v * 4.0, (u + v) * 1.5], -1).astype(np.uint8)
    K = np.array([[80.0, 0, 45.0], [0, 80.0, 30.0], [0, 0, 1]])
    back = ud.undistort_image(ud.distort_image(img, K, dist), K, dist)
    assert np.abs(back.astype(float) - img)[6:-6, 6:-6].max() <= 2.0
    assert ud.undistort_image(img, K, (0, 0, 0, 0, 0)) is img


@pytest.mark.slow
def test_waymo_segment_builds_through_ingest_and_fit(source, tmp_path):
    from paradrive.pipeline import StageRegistry, run_build

    path = tmp_path / "logs" / SEGMENT
    export.export_waymo(source, path, distortion=DIST)
    config = StageRegistry().resolve("smoke", {"fit": {"checkpoints": [5, 10, 15, 20]},
                                               "render": {"clip_frames": 4}})  # a 4-frame log
    report = run_build(config, [f"waymo:{path}"], tmp_path / "data", stages=["ingest", "fit"])
    assert [f.error for f in report.failures()] == []
    scene_dir = tmp_path / "data" / "scenes" / "waymo-1234"
    assert (scene_dir / "scene.json").is_file() and (scene_dir / "lidar" / "000000.npy").is_file()
    assert (scene_dir / "gs" / "ckpt_000020.ply").is_file()
    # ingest.cameras: auto, the Waymo fit set (the three front cameras), all of them fitted
    fitted = json.loads((scene_dir / "gs" / "fit.json").read_text())
    assert fitted["cameras"] == sorted(CAMS) and fitted["n_views"] == 4 * len(CAMS)
