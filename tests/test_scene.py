"""The canonical scene: scene.json round trip and validation errors that name scene, file and fix."""

import json

import numpy as np
import pytest

from paradrive import geometry as g
from paradrive.errors import SceneError
from paradrive.scene import (Camera, Frame, FrameCamera, Scene, load_scene, read_image,
                             write_image, write_scene)


def make_scene(root, n=4, ext="png"):
    cam2ego = g.make_pose(g.OPENCV_TO_FLU, [1.5, 0, 1.6])
    cam = Camera("front", 32, 24, 30.0, 30.0, 16.0, 12.0, cam2ego)
    frames = []
    for i in range(n):
        ego = g.translation(x=0.8 * i)
        rel = f"images/front/{i:06d}.{ext}"
        write_image(root / rel, np.full((24, 32, 3), 10 * i, np.uint8))
        frames.append(Frame(i, i * 100_000, ego, {"front": FrameCamera(rel, ego @ cam2ego)}))
    scene = Scene("test-scene", "synthetic", "synthetic:test", 10.0, {"front": cam}, frames, root=root)
    write_scene(scene, root)
    return scene


def test_scene_json_round_trip(tmp_path):
    scene = make_scene(tmp_path)
    doc = json.loads((tmp_path / "scene.json").read_text())
    assert doc["schema_version"] == 2 and doc["world"] == "first ego pose"
    assert len(doc["cameras"]["front"]["cam2ego"]) == 16
    assert doc["frames"][2]["cameras"]["front"]["image"] == "images/front/000002.png"
    loaded = load_scene(tmp_path)
    np.testing.assert_array_equal(loaded.c2w("front"), scene.c2w("front"))
    assert loaded.cameras["front"].K()[0, 2] == 16.0
    assert loaded.load_image(3, "front")[0, 0, 0] == 30


def test_missing_image_names_scene_and_file(tmp_path):
    make_scene(tmp_path)
    (tmp_path / "images/front/000002.png").unlink()
    with pytest.raises(SceneError, match=r"scene test-scene: frame 2 camera front image is missing .*000002.png"):
        load_scene(tmp_path)


def test_nan_pose_is_rejected_with_a_fix(tmp_path):
    make_scene(tmp_path)
    doc = json.loads((tmp_path / "scene.json").read_text())
    doc["frames"][1]["ego2world"][3] = float("nan")
    (tmp_path / "scene.json").write_text(json.dumps(doc))
    with pytest.raises(SceneError, match=r"frame 1 ego pose has NaN .*scene.json.*fix or drop the frame"):
        load_scene(tmp_path)


def test_non_rigid_pose_is_rejected(tmp_path):
    make_scene(tmp_path)
    doc = json.loads((tmp_path / "scene.json").read_text())
    pose = np.array(doc["frames"][0]["cameras"]["front"]["c2w"]).reshape(4, 4)
    pose[:3, :3] *= 2.0
    doc["frames"][0]["cameras"]["front"]["c2w"] = pose.reshape(-1).tolist()
    (tmp_path / "scene.json").write_text(json.dumps(doc))
    with pytest.raises(SceneError, match="frame 0 camera front pose is not rigid"):
        load_scene(tmp_path)


def test_bad_intrinsics_are_rejected(tmp_path):
    make_scene(tmp_path)
    doc = json.loads((tmp_path / "scene.json").read_text())
    doc["cameras"]["front"]["fx"] = -3.0
    (tmp_path / "scene.json").write_text(json.dumps(doc))
    with pytest.raises(SceneError, match="camera front has bad intrinsics"):
        load_scene(tmp_path)


def test_timestamps_out_of_order_are_rejected(tmp_path):
    make_scene(tmp_path)
    doc = json.loads((tmp_path / "scene.json").read_text())
    doc["frames"][3]["timestamp_us"] = doc["frames"][1]["timestamp_us"]
    (tmp_path / "scene.json").write_text(json.dumps(doc))
    with pytest.raises(SceneError, match="frame 3 timestamp .* out of order"):
        load_scene(tmp_path)


def test_missing_scene_json_says_run_ingest(tmp_path):
    with pytest.raises(SceneError, match="scene.json is missing .*run the ingest stage"):
        load_scene(tmp_path)


def test_truncated_jpeg_is_a_scene_error(tmp_path):
    path = tmp_path / "x.jpg"
    write_image(path, (np.random.default_rng(0).random((48, 64, 3)) * 255).astype(np.uint8))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(SceneError, match=r"scene s1: image is corrupt or truncated.*x.jpg"):
        read_image(path, scene_id="s1")


def test_write_image_leaves_no_temporary_on_success(tmp_path):
    write_image(tmp_path / "a.png", np.zeros((4, 4, 3), np.uint8))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png"]


def _png_scanline_filters(path) -> tuple[int, bytes]:
    """(width, the filter byte of each scanline) of an 8-bit RGB PNG, from its IDAT stream."""
    import struct
    import zlib

    data = path.read_bytes()
    pos, width, idat = 8, 0, b""
    while pos < len(data):
        (length,), kind = struct.unpack(">I", data[pos:pos + 4]), data[pos + 4:pos + 8]
        body = data[pos + 8:pos + 8 + length]
        if kind == b"IHDR":
            width = struct.unpack(">I", body[:4])[0]
        elif kind == b"IDAT":
            idat += body
        pos += 12 + length
    raw = zlib.decompress(idat)
    return width, raw[::1 + 3 * width]


def test_png_frames_are_written_lossless_with_the_fast_up_filter(tmp_path):
    rng = np.random.default_rng(0)
    pixels = np.clip(np.linspace(0, 255, 40)[None, :, None] + rng.normal(0, 8, (30, 40, 3)),
                     0, 255).astype(np.uint8)
    write_image(tmp_path / "frame.png", pixels)
    assert np.array_equal(read_image(tmp_path / "frame.png"), pixels)
    width, filters = _png_scanline_filters(tmp_path / "frame.png")
    assert width == 40 and len(filters) == 30
    # libpng's "up" filter (type 2) on every row: the encoder does not try the others per row
    assert set(filters) == {2}, sorted(set(filters))
