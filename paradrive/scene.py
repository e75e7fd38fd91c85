"""The canonical scene: ``scene.json`` + undistorted images, as docs/scene-layout.md fixes them.

Layout under ``<data>/scenes/<scene_id>/``::

    scene.json
    images/<cam>/<frame:06d>.<ext>
    masks/sky/<cam>/<frame:06d>.png     (optional, 255 = sky)
    lidar/<frame:06d>.npy               (optional, (M, 3) float32 world points)
    masks/dynamic/<cam>/<frame:06d>.png (with actors, 255 = a moving actor's box)

Schema 2 adds ``actors`` (paradrive.actors); schema 1 files (no actors) still load.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from paradrive import geometry
from paradrive.actors import Actor, actor_from_json
from paradrive.contracts.layout import SceneLayout
from paradrive.errors import SceneError
from paradrive.io import (PathEscapeError, atomic_path, check_relative, encoded_in_memory, path_inside,
                          write_bytes, write_json)

SCHEMA_VERSION = 2
# versions load_scene reads: 1 is 2 without actors
READABLE_VERSIONS = (1, 2)
CAMERA_NAMES = ("front", "front_left", "front_right", "side_left", "side_right",
                "back", "back_left", "back_right")


# --------------------------------------------------------------------------- images

def read_image(path: str | Path, *, scene_id: str | None = None) -> np.ndarray:
    """Read an RGB image as uint8 (H, W, 3); a missing, unreadable or truncated file is a SceneError."""
    import OpenImageIO as oiio

    path = Path(path)
    if not path.is_file():
        raise SceneError("image file is missing", scene_id=scene_id, path=path,
                         fix="re-run ingest for this scene or restore the file")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise SceneError(f"image cannot be opened: {oiio.geterror()}", scene_id=scene_id,
                         path=path, fix="re-run ingest or replace the file")
    try:
        pixels = inp.read_image(0, 0, 0, 3, "uint8")
        error = inp.geterror()
    finally:
        inp.close()
    if pixels is None or error:
        raise SceneError(f"image is corrupt or truncated: {error or 'no pixels'}",
                         scene_id=scene_id, path=path, fix="re-run ingest or replace the file")
    pixels = np.asarray(pixels)
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    if pixels.shape[2] == 1:
        pixels = np.repeat(pixels, 3, axis=2)
    return np.ascontiguousarray(pixels[..., :3])


# PNG writing: zlib level 1 with libpng's "up" row filter only. Measured on a 320x192 render:
# 2.5 ms and 81 kB a frame, against 14.8 ms and 70 kB with the defaults (level 6, every filter
# tried per row); a render stage writes thousands of them.
PNG_LEVEL = 1
PNG_FILTER_UP = 0x20


def write_image(path: str | Path, pixels: np.ndarray, *, quality: int = 95) -> None:
    """Write uint8 (H, W, C) pixels atomically; the format follows the extension (jpg, png, ...).

    The image is encoded in memory and then written as bytes (:func:`encoded_in_memory`), so a
    full disk raises :class:`~paradrive.errors.DiskFullError` naming the file: written
    directly, libjpeg would end the process and libpng would leave a truncated file."""
    import OpenImageIO as oiio

    path = Path(path)
    pixels = np.ascontiguousarray(pixels)
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    h, w, c = pixels.shape
    spec = oiio.ImageSpec(w, h, c, "uint8")
    if path.suffix.lower() in (".jpg", ".jpeg"):
        spec.attribute("Compression", f"jpeg:{quality}")
    elif path.suffix.lower() == ".png":
        spec.attribute("png:compressionLevel", PNG_LEVEL)
        spec.attribute("png:filter", PNG_FILTER_UP)

    def encode(target: str) -> None:
        out = oiio.ImageOutput.create(str(path))  # the format from the extension
        if out is None or not out.open(target, spec):
            raise OSError(f"cannot write image {path}: {oiio.geterror()}")
        ok = out.write_image(pixels)
        out.close()
        if not ok:
            raise OSError(f"cannot write image {path}: {out.geterror()}")

    data = encoded_in_memory(encode)
    if data is not None:
        write_bytes(path, data)
        return
    with atomic_path(path) as tmp:
        # OpenImageIO picks the format from the extension: keep it on the temporary name.
        tmp_with_ext = tmp.with_name(tmp.name + path.suffix)
        try:
            encode(str(tmp_with_ext))
        except OSError:
            tmp_with_ext.unlink(missing_ok=True)
            raise
        tmp_with_ext.rename(tmp)


# --------------------------------------------------------------------------- data model

@dataclass
class Camera:
    """A pinhole camera of the rig, in pixels of the stored (undistorted) images."""

    name: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    cam2ego: np.ndarray  # (4, 4) OpenCV camera -> ego

    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def to_json(self) -> dict:
        return {"width": int(self.width), "height": int(self.height),
                "fx": float(self.fx), "fy": float(self.fy), "cx": float(self.cx), "cy": float(self.cy),
                "cam2ego": geometry.as_floats(self.cam2ego)}


@dataclass
class FrameCamera:
    image: str           # relative to the scene root
    c2w: np.ndarray      # (4, 4) camera-to-world, OpenCV, scene world

    def to_json(self) -> dict:
        return {"image": self.image, "c2w": geometry.as_floats(self.c2w)}


@dataclass
class Frame:
    index: int
    timestamp_us: int
    ego2world: np.ndarray
    cameras: dict[str, FrameCamera]

    def to_json(self) -> dict:
        return {"index": int(self.index), "timestamp_us": int(self.timestamp_us),
                "ego2world": geometry.as_floats(self.ego2world),
                "cameras": {k: v.to_json() for k, v in self.cameras.items()}}


@dataclass
class Scene:
    scene_id: str
    dataset: str
    source: str
    fps: float
    cameras: dict[str, Camera]
    frames: list[Frame]
    root: Path | None = None
    extra: dict = field(default_factory=dict)
    actors: list[Actor] = field(default_factory=list)

    # ---------------------------------------------------------------- poses
    def c2w(self, camera: str) -> np.ndarray:
        """Camera-to-world poses (F, 4, 4) of ``camera`` over all frames."""
        return np.stack([f.cameras[camera].c2w for f in self.frames])

    def ego2world(self) -> np.ndarray:
        """Ego poses (F, 4, 4)."""
        return np.stack([f.ego2world for f in self.frames])

    def timestamps_us(self) -> np.ndarray:
        return np.array([f.timestamp_us for f in self.frames], dtype=np.int64)

    # ---------------------------------------------------------------- files
    def _require_root(self) -> Path:
        if self.root is None:
            raise ValueError(f"scene {self.scene_id} has no root folder")
        return self.root

    def image_path(self, frame_index: int, camera: str) -> Path:
        """The image file, checked to stay inside the scene folder (scene.json may be shared)."""
        root = self._require_root()
        frame = self.frames[frame_index]
        try:
            return path_inside(root, frame.cameras[camera].image,
                               f"{root / 'scene.json'}: frame {frame.index} camera {camera} image")
        except PathEscapeError as exc:
            raise SceneError(str(exc), scene_id=self.scene_id) from exc

    def load_image(self, frame_index: int, camera: str) -> np.ndarray:
        """uint8 (H, W, 3) of frame ``frame_index`` (position in ``frames``) and ``camera``."""
        return read_image(self.image_path(frame_index, camera), scene_id=self.scene_id)

    def sky_mask_path(self, frame_index: int, camera: str) -> Path:
        index = self.frames[frame_index].index
        return SceneLayout(self._require_root()).sky_mask(camera, index)

    def sky_mask(self, frame_index: int, camera: str) -> np.ndarray | None:
        """bool (H, W), True = sky, or None when the scene has no sky masks."""
        path = self.sky_mask_path(frame_index, camera)
        if not path.is_file():
            return None
        return read_image(path, scene_id=self.scene_id)[..., 0] > 127

    def lidar_frame(self, frame_index: int) -> np.ndarray | None:
        """LiDAR points (M, 3) float32 in the scene world of frame ``frame_index`` (position in
        ``frames``), or None when that frame has none."""
        path = SceneLayout(self._require_root()).lidar(self.frames[frame_index].index)
        if not path.is_file():
            return None
        return np.load(path).astype(np.float32).reshape(-1, 3)

    def lidar_points(self, max_frames: int | None = None) -> np.ndarray | None:
        """All LiDAR points (M, 3) float32 in the scene world, or None when the scene has none."""
        folder = SceneLayout(self._require_root()).lidar_dir
        files = sorted(folder.glob("*.npy")) if folder.is_dir() else []
        if not files:
            return None
        if max_frames and len(files) > max_frames:
            files = files[:: math.ceil(len(files) / max_frames)]
        return np.concatenate([np.load(f).astype(np.float32).reshape(-1, 3) for f in files])

    # ---------------------------------------------------------------- json
    def to_json(self) -> dict:
        doc = {"schema_version": SCHEMA_VERSION, "scene_id": self.scene_id, "dataset": self.dataset,
               "source": self.source, "fps": float(self.fps), "world": "first ego pose",
               "cameras": {k: v.to_json() for k, v in self.cameras.items()},
               "frames": [f.to_json() for f in self.frames],
               "actors": [a.to_json() for a in self.actors]}
        for key, value in self.extra.items():
            doc.setdefault(key, value)
        return doc


# --------------------------------------------------------------------------- I/O

def scene_from_json(doc: dict, root: Path | None = None) -> Scene:
    """Build a Scene from a parsed scene.json; structural problems are SceneErrors."""
    sid = doc.get("scene_id", "?")
    where = (root / "scene.json") if root else "scene.json"
    try:
        cameras = {name: Camera(name=name, width=int(c["width"]), height=int(c["height"]),
                                fx=float(c["fx"]), fy=float(c["fy"]), cx=float(c["cx"]),
                                cy=float(c["cy"]), cam2ego=geometry.as_pose(c["cam2ego"]))
                   for name, c in doc["cameras"].items()}
        frames = [Frame(index=int(f["index"]), timestamp_us=int(f["timestamp_us"]),
                        ego2world=geometry.as_pose(f["ego2world"]),
                        cameras={k: FrameCamera(image=v["image"], c2w=geometry.as_pose(v["c2w"]))
                                 for k, v in f["cameras"].items()})
                  for f in doc["frames"]]
        known = {"schema_version", "scene_id", "dataset", "source", "fps", "world", "cameras",
                 "frames", "actors"}
        return Scene(scene_id=doc["scene_id"], dataset=doc["dataset"], source=doc["source"],
                     fps=float(doc["fps"]), cameras=cameras, frames=frames, root=root,
                     extra={k: v for k, v in doc.items() if k not in known},
                     actors=[actor_from_json(a) for a in doc.get("actors", [])])
    except (KeyError, TypeError, ValueError) as exc:
        raise SceneError(f"scene.json is malformed: {type(exc).__name__}: {exc}", scene_id=sid,
                         path=where, fix="re-run ingest for this scene") from exc


def load_scene(scene_dir: str | Path, *, check_files: bool = True) -> Scene:
    """Read and validate ``<scene_dir>/scene.json``."""
    root = Path(scene_dir)
    path = SceneLayout(root).scene_json
    if not path.is_file():
        raise SceneError("scene.json is missing", scene_id=root.name, path=path,
                         fix="run the ingest stage for this scene first")
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise SceneError(f"scene.json is not valid JSON ({exc})", scene_id=root.name, path=path,
                         fix="re-run ingest for this scene") from exc
    scene = scene_from_json(doc, root)
    if doc.get("schema_version") not in READABLE_VERSIONS:
        raise SceneError(f"scene.json schema_version {doc.get('schema_version')!r} is not one of "
                         f"{READABLE_VERSIONS}", scene_id=scene.scene_id, path=path,
                         fix="re-ingest the scene with this version of paradrive")
    validate_scene(scene, check_files=check_files)
    return scene


def write_scene(scene: Scene, scene_dir: str | Path | None = None) -> Path:
    """Validate (poses, intrinsics, order; not files) and write ``scene.json`` atomically."""
    root = Path(scene_dir) if scene_dir is not None else scene._require_root()
    validate_scene(scene, check_files=False)
    path = SceneLayout(root).scene_json
    write_json(path, scene.to_json())
    scene.root = root
    return path


def validate_scene(scene: Scene, *, check_files: bool = True) -> None:
    """Raise SceneError naming the scene, the file and the fix for the first problem found.

    Checks: cameras have positive size and focal lengths with the principal point inside the
    image; every pose is finite and rigid; timestamps strictly increase; every frame names an
    image for known cameras (and, with ``check_files``, the image exists).
    """
    sid = scene.scene_id
    root = scene.root
    where = (root / "scene.json") if root else "scene.json"
    if not scene.cameras:
        raise SceneError("scene has no cameras", scene_id=sid, path=where,
                         fix="check the log's calibration records")
    if not scene.frames:
        raise SceneError("scene has no frames", scene_id=sid, path=where,
                         fix="check the log: it holds no camera frames")
    if not (math.isfinite(scene.fps) and scene.fps > 0):
        raise SceneError(f"fps {scene.fps} is not positive", scene_id=sid, path=where,
                         fix="re-ingest with a valid frame rate")
    for name, cam in scene.cameras.items():
        values = [cam.fx, cam.fy, cam.cx, cam.cy]
        if (cam.width <= 0 or cam.height <= 0 or not all(map(math.isfinite, values))
                or cam.fx <= 0 or cam.fy <= 0
                or not (0 <= cam.cx <= cam.width) or not (0 <= cam.cy <= cam.height)):
            raise SceneError(
                f"camera {name} has bad intrinsics (width={cam.width}, height={cam.height}, "
                f"fx={cam.fx}, fy={cam.fy}, cx={cam.cx}, cy={cam.cy})", scene_id=sid, path=where,
                fix="check the calibration: focal lengths must be positive and the principal "
                    "point inside the image")
        if not geometry.is_rigid(cam.cam2ego):
            raise SceneError(f"camera {name} cam2ego is not a rigid transform", scene_id=sid,
                             path=where, fix="check the camera extrinsic calibration")
    previous = None
    for pos, frame in enumerate(scene.frames):
        label = f"frame {frame.index}"
        if not geometry.is_rigid(frame.ego2world):
            problem = "has NaN" if not np.isfinite(frame.ego2world).all() else "is not rigid"
            raise SceneError(f"{label} ego pose {problem}", scene_id=sid, path=where,
                             fix="fix or drop the frame in the log")
        if previous is not None and frame.timestamp_us <= previous:
            raise SceneError(f"{label} timestamp {frame.timestamp_us} us is not after the previous "
                             f"frame's {previous} us (timestamps out of order)", scene_id=sid,
                             path=where, fix="sort the frames by time or drop duplicates")
        previous = frame.timestamp_us
        for cam_name, fc in frame.cameras.items():
            if cam_name not in scene.cameras:
                raise SceneError(f"{label} names camera {cam_name!r} that has no calibration",
                                 scene_id=sid, path=where,
                                 fix="add its calibration or drop the camera")
            if not geometry.is_rigid(fc.c2w):
                problem = "has NaN" if not np.isfinite(fc.c2w).all() else "is not rigid"
                raise SceneError(f"{label} camera {cam_name} pose {problem}", scene_id=sid,
                                 path=where, fix="fix or drop the frame in the log")
            try:
                check_relative(fc.image, f"{label} camera {cam_name} image")
            except PathEscapeError as exc:
                raise SceneError(str(exc), scene_id=sid, path=where) from exc
            if check_files and root is not None and not (root / fc.image).is_file():
                raise SceneError(f"{label} camera {cam_name} image is missing", scene_id=sid,
                                 path=root / fc.image, fix="re-run ingest for this scene")
