"""Helpers the log readers (waymo, nuscenes, drivestudio) share: poses, images, checks."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from paradrive import geometry
from paradrive.errors import SceneError
from paradrive.ingest.undistort import distortion_is_zero, undistort_image
from paradrive.scene import write_image
from paradrive.io import counted_stop, write_bytes

# OpenCV camera axes -> "vehicle-style" camera axes (x forward, y left, z up), as a 4x4.
OPENCV_TO_FLU = geometry.make_pose(geometry.OPENCV_TO_FLU, np.zeros(3))


def checked_pose(matrix, *, scene_id: str, where, what: str) -> np.ndarray:
    """A (4, 4) float64 pose; SceneError when it has NaN/inf or is not rigid."""
    try:
        pose = geometry.as_pose(np.asarray(matrix, dtype=np.float64))
    except ValueError as exc:
        raise SceneError(f"{what} is not a 4x4 pose ({exc})", scene_id=scene_id, path=where,
                         fix="fix or drop the record in the log") from exc
    if pose.shape != (4, 4):
        raise SceneError(f"{what} has shape {pose.shape}, expected 4x4", scene_id=scene_id,
                         path=where, fix="fix or drop the record in the log")
    if not np.isfinite(pose).all():
        raise SceneError(f"{what} has NaN", scene_id=scene_id, path=where,
                         fix="fix or drop the frame in the log")
    if not geometry.is_rigid(pose, tol=1e-4):
        raise SceneError(f"{what} is not a rigid transform", scene_id=scene_id, path=where,
                         fix="fix the pose or calibration in the log")
    return pose


def check_increasing(stamps: list[int], *, scene_id: str, where, labels: list[str]) -> None:
    """SceneError naming the first timestamp that does not increase."""
    for i in range(1, len(stamps)):
        if stamps[i] <= stamps[i - 1]:
            raise SceneError(
                f"{labels[i]} timestamp {stamps[i]} us is not after {labels[i - 1]}'s "
                f"{stamps[i - 1]} us (non-monotonic timestamps)", scene_id=scene_id, path=where,
                fix="sort the frames by time or drop the duplicate")


def fps_from(stamps: list[int], default: float) -> float:
    if len(stamps) < 2:
        return float(default)
    dt = float(np.median(np.diff(np.asarray(stamps, dtype=np.int64))))
    return 1e6 / dt if dt > 0 else float(default)


def decode_jpeg(data, *, scene_id: str, where) -> np.ndarray:
    """uint8 (H, W, 3) pixels of encoded image bytes; SceneError when they do not decode."""
    from PIL import Image

    try:
        with Image.open(io.BytesIO(bytes(data))) as im:
            im.load()
            return np.asarray(im.convert("RGB"))
    except Exception as exc:  # PIL raises many kinds for corrupt data
        raise SceneError(f"image does not decode ({type(exc).__name__}: {exc})",
                         scene_id=scene_id, path=where,
                         fix="the log's image is corrupt: re-download it or drop the frame") from exc


def encode_jpeg(pixels: np.ndarray, quality: int = 95) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(pixels)).save(buf, format="JPEG", quality=int(quality),
                                                       subsampling=0)
    return buf.getvalue()


def store_image(out_dir: Path, rel: str, pixels: np.ndarray, *, K=None, dist=None,
                quality: int = 95, original: bytes | None = None) -> None:
    """Undistort (when ``dist`` is non-zero) and write an image under ``out_dir``.

    When nothing changes the pixels and the target is JPEG, the original JPEG bytes are kept
    as they are (no second lossy encode).
    """
    target = out_dir / rel
    if distortion_is_zero(dist):
        if original is not None and target.suffix.lower() in (".jpg", ".jpeg"):
            write_bytes(target, bytes(original))
            image_written()
            return
    else:
        pixels = undistort_image(pixels, K, dist)
    write_image(target, pixels, quality=quality)
    image_written()


# each camera image an ingest writes, for the tests that stop a build at its k-th
# (PARADRIVE_STOP_AT=ingest:image-<k>)
image_written = counted_stop("ingest:image")


def check_size(pixels: np.ndarray, width: int, height: int, *, scene_id: str, where,
               what: str) -> None:
    h, w = pixels.shape[:2]
    if (w, h) != (int(width), int(height)):
        raise SceneError(f"{what} is {w}x{h} but its calibration says {width}x{height}",
                         scene_id=scene_id, path=where,
                         fix="use the calibration that belongs to these images")


def save_points(out_dir: Path, index: int, points_world: np.ndarray) -> None:
    from paradrive.io import atomic_path

    path = out_dir / "lidar" / f"{index:06d}.npy"
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, np.asarray(points_world, dtype=np.float32).reshape(-1, 3))


def transform_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a pose (4, 4) to points (M, 3)."""
    return points @ pose[:3, :3].T + pose[:3, 3]

