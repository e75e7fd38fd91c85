"""``waymo:<segment.tfrecord>`` and ``waymo:<folder>[#<segment>]``: Waymo Open Dataset (perception).

A segment is a TFRecord file of ``Frame`` protos (about 200 frames at 10 Hz). Per frame the
builder reads the vehicle pose and timestamp, and per camera the JPEG with the vehicle pose it
was taken at (``CameraImage.pose``, which differs from the frame pose by the rolling-shutter
time offset). The first frame's context gives the calibrations:
intrinsic ``[f_u, f_v, c_u, c_v, k1, k2, p1, p2, k3]`` and the extrinsic camera -> vehicle,
with the camera frame x forward, y left, z up. So, with world = the first vehicle pose::

    c2w = inv(pose_0) · image_pose · extrinsic · OPENCV_TO_FLU

Images are undistorted here; the stored intrinsics are the pinhole part.
With ``lidar`` on, the TOP laser's first-return range image (zlib-compressed MatrixFloat,
per-pixel vehicle poses when given) becomes world points ``lidar/<frame>.npy``.
Each frame's ``laser_labels`` (upright boxes in that frame's vehicle frame, with a tracking id)
become the scene's actors: ``box2world = inv(pose_0) · pose_t · box(centre, heading)``.
"""

from __future__ import annotations

import math
import re
import zlib
from pathlib import Path
from typing import Any, TYPE_CHECKING

import numpy as np

from paradrive import actors as act
from paradrive import geometry
from paradrive.errors import SceneError
from paradrive.ingest import select_cameras
from paradrive.ingest import waymo_proto as wp
from paradrive.ingest.common import (
    OPENCV_TO_FLU, check_size, checked_pose, decode_jpeg, fps_from, save_points,
    store_image, transform_points,
)
from paradrive.ingest.protowire import WireError, decode
from paradrive.ingest.tfrecord import RecordError, iter_records
from paradrive.scene import Camera, Frame, FrameCamera, Scene
from paradrive.uri import SceneURI

if TYPE_CHECKING:
    from paradrive.contracts.params import IngestParams

SUFFIXES = (".tfrecord", ".tfrecords")
FPS = 10.0


def camera_name(waymo_id: int) -> str:
    """Waymo CameraName enum value -> the builder's camera name (FRONT_LEFT -> front_left)."""
    return wp.CAMERA_NAMES.get(int(waymo_id), f"camera_{int(waymo_id)}").lower()


def segment_stem(name: str) -> str:
    """``segment-123_with_camera_labels.tfrecord`` -> ``123``."""
    stem = re.sub(r"\.tfrecords?$", "", Path(name).name)
    stem = re.sub(r"^segment-", "", stem)
    return re.sub(r"_with_camera_labels$", "", stem)


def list_segments(folder: str | Path) -> list[str]:
    """Scene URIs of every segment (``*.tfrecord``) in ``folder``, sorted by name."""
    folder = Path(folder)
    return [f"waymo:{p}" for p in sorted(folder.iterdir())
            if p.is_file() and p.suffix in SUFFIXES and not p.name.startswith(".")]


def resolve_segment(uri: SceneURI, scene_id: str) -> Path:
    """The segment file a URI names (a file, or a folder plus ``#<segment>``)."""
    path = Path(uri.path).expanduser()
    if path.is_file():
        return path
    if not path.exists():
        raise SceneError("segment file or folder does not exist", scene_id=scene_id, path=path,
                         fix="check the path in the scene URI")
    segments = [Path(u.split(":", 1)[1]) for u in list_segments(path)]
    if uri.scene:
        want = segment_stem(uri.scene)
        hits = [p for p in segments if segment_stem(p.name) == want or p.name == uri.scene]
        if not hits:
            raise SceneError(f"no segment {uri.scene!r} in the folder ({len(segments)} segments)",
                             scene_id=scene_id, path=path,
                             fix="check the name after '#' against the folder's .tfrecord files")
        return hits[0]
    if len(segments) == 1:
        return segments[0]
    raise SceneError(f"folder holds {len(segments)} segments, not one", scene_id=scene_id,
                     path=path, fix="name one with '#<segment>' or pass the folder with --scenes "
                                    "to build each segment")


# --------------------------------------------------------------------------- frames

def iter_frames(segment: Path, scene_id: str):
    """Yield (record index, decoded Frame); corrupt records are SceneErrors naming the record."""
    try:
        for index, data in enumerate(iter_records(segment)):
            try:
                yield index, wp.decode_frame(data)
            except WireError as exc:
                raise SceneError(f"record {index} is not a Waymo Frame ({exc})",
                                 scene_id=scene_id, path=segment,
                                 fix="check that the file is a Waymo Open Dataset perception "
                                     "segment") from exc
    except RecordError as exc:
        raise SceneError(f"corrupt TFRecord: {exc}", scene_id=scene_id, path=segment,
                         fix="re-download the segment (the file is damaged or cut short)") from exc


def transform_of(msg, *, scene_id: str, where, what: str) -> np.ndarray:
    values = [] if msg is None else list(msg.transform)
    if len(values) != 16:
        raise SceneError(f"{what} has {len(values)} numbers, expected 16", scene_id=scene_id,
                         path=where, fix="the segment is incomplete; re-download it")
    return checked_pose(np.asarray(values).reshape(4, 4), scene_id=scene_id, where=where,
                        what=what)


def camera_calibrations(context, *, scene_id: str, where) -> dict[str, Any]:
    return {camera_name(c.name): c for c in (context.camera_calibrations if context else [])}


def euler_pose(rpy_xyz: np.ndarray) -> np.ndarray:
    """Poses (..., 4, 4) from [roll, pitch, yaw, x, y, z] (R = Rz(yaw) Ry(pitch) Rx(roll))."""
    roll, pitch, yaw = rpy_xyz[..., 0], rpy_xyz[..., 1], rpy_xyz[..., 2]
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    rot = np.stack([
        np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
        np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
        np.stack([-sp, cp * sr, cp * cr], -1),
    ], -2)
    return geometry.make_pose(rot, rpy_xyz[..., 3:6])


def matrix_float(compressed, *, channels: int) -> np.ndarray:
    """zlib-compressed serialized MatrixFloat -> float32 (H, W, channels)."""
    m = decode(wp.MatrixFloat, zlib.decompress(bytes(compressed)))
    dims = list(m.shape.dims) if m.shape is not None else []
    data = np.asarray(m.data, dtype=np.float32)
    if len(dims) != 3 or dims[2] != channels or int(np.prod(dims)) != data.size:
        raise ValueError(f"matrix shape {dims} does not hold {data.size} values of "
                         f"{channels} channels")
    return data.reshape(dims)


def beam_inclinations(calib, height: int) -> np.ndarray:
    """Inclination (rad) of each range-image row; row 0 is the highest beam."""
    if calib.beam_inclinations:
        incl = np.asarray(calib.beam_inclinations, dtype=np.float64)
    else:
        lo, hi = calib.beam_inclination_min, calib.beam_inclination_max
        incl = lo + (np.arange(height) + 0.5) / height * (hi - lo)
    return incl[::-1]


def range_image_points(range_image: np.ndarray, extrinsic: np.ndarray, inclinations: np.ndarray,
                       pixel_pose: np.ndarray | None = None) -> np.ndarray:
    """Points (M, 3) of a range image (H, W, >=1 channel; channel 0 range, <= 0 means none).

    In the vehicle frame, or in the global frame when ``pixel_pose`` (H, W, 4, 4) is given.
    """
    h, w = range_image.shape[:2]
    rng = range_image[..., 0].astype(np.float64)
    az_correction = math.atan2(extrinsic[1, 0], extrinsic[0, 0])
    ratios = (np.arange(w, 0, -1, dtype=np.float64) - 0.5) / w
    azimuth = (ratios * 2.0 - 1.0) * np.pi - az_correction
    incl = inclinations[:, None]
    pts = np.stack([np.cos(azimuth)[None, :] * np.cos(incl) * rng,
                    np.sin(azimuth)[None, :] * np.cos(incl) * rng,
                    np.sin(incl) * rng], axis=-1)
    pts = pts @ extrinsic[:3, :3].T + extrinsic[:3, 3]
    if pixel_pose is not None:
        pts = np.einsum("hwij,hwj->hwi", pixel_pose[..., :3, :3], pts) + pixel_pose[..., :3, 3]
    return pts[rng > 0]


def top_lidar_points(frame, context, frame_pose: np.ndarray, world_from_global: np.ndarray,
                     *, scene_id: str, where) -> np.ndarray | None:
    """World points of the TOP laser's first return, or None when the frame has none."""
    calib = next((c for c in (context.laser_calibrations if context else [])
                  if c.name == wp.LASER_IDS["TOP"]), None)
    laser = next((l for l in frame.lasers if l.name == wp.LASER_IDS["TOP"]), None)
    if calib is None or laser is None or laser.ri_return1 is None:
        return None
    ri = laser.ri_return1
    if not len(ri.range_image_compressed):
        return None
    try:
        image = matrix_float(ri.range_image_compressed, channels=4)
        pixel_pose = None
        if len(ri.range_image_pose_compressed):
            rpy = matrix_float(ri.range_image_pose_compressed, channels=6).astype(np.float64)
            if rpy.shape[:2] != image.shape[:2]:
                raise ValueError(f"pose image {rpy.shape[:2]} vs range image {image.shape[:2]}")
            pixel_pose = euler_pose(rpy)
    except (zlib.error, WireError, ValueError) as exc:
        raise SceneError(f"TOP lidar range image is corrupt ({exc})", scene_id=scene_id,
                         path=where, fix="re-download the segment or ingest with lidar off") from exc
    extrinsic = transform_of(calib.extrinsic, scene_id=scene_id, where=where,
                             what="TOP lidar extrinsic")
    incl = beam_inclinations(calib, image.shape[0])
    if incl.size != image.shape[0]:
        raise SceneError(f"TOP lidar has {incl.size} beam inclinations for {image.shape[0]} rows",
                         scene_id=scene_id, path=where, fix="ingest with lidar off")
    pts = range_image_points(image, extrinsic, incl, pixel_pose)
    to_world = world_from_global if pixel_pose is not None else world_from_global @ frame_pose
    return transform_points(to_world, pts)


# --------------------------------------------------------------------------- labels

def label_class(label) -> tuple[str, bool] | None:
    """(class, rigid) of a laser label; None for signs and unknowns; KeyError for other types."""
    if label.type in act.WAYMO_DROPPED_TYPES:
        return None
    cls = act.WAYMO_TYPES[label.type]
    return cls, cls == "vehicle"


def label_actors(labels: list[list], vehicle2world: list[np.ndarray], *, scene_id: str,
                 where) -> list[act.Actor]:
    """Tracks of the laser labels of each frame (labels[i]), placed with vehicle2world[i]."""
    boxes: dict[str, dict] = {}
    for index, (frame_labels, pose) in enumerate(zip(labels, vehicle2world)):
        for label in frame_labels:
            key = f"waymo:{label.id}"
            try:
                kind = label_class(label)
            except KeyError:
                act.log_dropped(key, f"type {label.type} is not a Waymo Label.Type (0-4)",
                                scene_id=scene_id, where=where)
                continue
            b = label.box
            if kind is None or b is None:
                continue
            entry = boxes.setdefault(key, {"kind": kind, "frames": [], "poses": [], "sizes": []})
            entry["frames"].append(index)
            entry["poses"].append(pose @ act.box_pose([b.center_x, b.center_y, b.center_z],
                                                      b.heading))
            entry["sizes"].append([b.length, b.width, b.height])
    found = [act.actor_from_boxes(key, e["kind"][0], e["kind"][1], e["frames"], e["poses"],
                                  e["sizes"]) for key, e in boxes.items()]
    return act.keep_valid(found, range(len(labels)), scene_id=scene_id, where=where)


# --------------------------------------------------------------------------- reader

def read(uri: SceneURI, out_dir: Path, params: IngestParams, scene_id: str) -> Scene:
    segment = resolve_segment(uri, scene_id)
    limit = params.max_frames
    ext, quality, want_lidar = params.image_ext, params.jpeg_quality, params.lidar

    cameras: dict[str, Camera] = {}
    calibs: dict[str, Any] = {}
    chosen: list[str] = []
    frames: list[Frame] = []
    stamps: list[int] = []
    labels: list[list] = []
    world_from_global = None
    context = None
    segment_name = None
    for record, msg in iter_frames(segment, scene_id):
        if limit is not None and len(frames) >= limit:
            break
        where = f"{segment} record {record}"
        if msg.context is not None and msg.context.camera_calibrations:
            context = context or msg.context
            segment_name = segment_name or msg.context.name
        if not calibs:
            if context is None:
                raise SceneError("first frame has no camera calibrations (Frame.context)",
                                 scene_id=scene_id, path=where,
                                 fix="check that the file is a full perception segment")
            calibs = camera_calibrations(context, scene_id=scene_id, where=where)
            chosen = select_cameras(list(calibs), params, "waymo", scene_id=scene_id,
                                    where=segment)
            for name in chosen:
                cameras[name] = _camera(name, calibs[name], scene_id=scene_id, where=where)
        stamp = _timestamp(msg, stamps, scene_id=scene_id, where=where)
        pose = transform_of(msg.pose, scene_id=scene_id, where=where,
                            what=f"frame {len(frames)} vehicle pose")
        if world_from_global is None:
            world_from_global = geometry.invert(pose)
        index = len(frames)
        images = {camera_name(im.name): im for im in msg.images}
        frame = Frame(index=index, timestamp_us=stamp, ego2world=world_from_global @ pose,
                      cameras={})
        for name in chosen:
            rel = f"images/{name}/{index:06d}.{ext}"
            c2w = _store_image(out_dir, rel, images.get(name), calibs[name], cameras[name], pose,
                               world_from_global, index, quality, scene_id=scene_id, where=where)
            frame.cameras[name] = FrameCamera(image=rel, c2w=c2w)
        if want_lidar:
            pts = top_lidar_points(msg, context, pose, world_from_global, scene_id=scene_id,
                                   where=where)
            if pts is not None:
                save_points(out_dir, index, pts)
        frames.append(frame)
        stamps.append(stamp)
        labels.append(list(msg.laser_labels))
    if not frames:
        raise SceneError("segment holds no frames", scene_id=scene_id, path=segment,
                         fix="check the file: it is empty")
    return Scene(scene_id=scene_id, dataset="waymo", source=uri.text,
                 fps=fps_from(stamps, FPS), cameras=cameras, frames=frames,
                 actors=label_actors(labels, [f.ego2world for f in frames], scene_id=scene_id,
                                     where=f"{segment} laser_labels"),
                 extra={"waymo": {"segment": segment_name or segment_stem(segment.name),
                                  "file": segment.name}})


def _timestamp(msg, stamps: list[int], *, scene_id: str, where: str) -> int:
    """The frame's timestamp (us), after the previous frame's (``stamps[-1]``)."""
    if not msg.has("timestamp_micros"):
        raise SceneError("frame has no timestamp_micros", scene_id=scene_id, path=where,
                         fix="the segment is incomplete; re-download it")
    stamp = int(msg.timestamp_micros)
    if stamps and stamp <= stamps[-1]:
        raise SceneError(f"frame {len(stamps)} timestamp {stamp} us is not after the previous "
                         f"frame's {stamps[-1]} us (non-monotonic timestamps)",
                         scene_id=scene_id, path=where,
                         fix="sort the segment's frames by time or drop the duplicate")
    return stamp


def _store_image(out_dir: Path, rel: str, im, calib, camera: Camera, pose: np.ndarray,
                 world_from_global: np.ndarray, index: int, quality: int, *, scene_id: str,
                 where: str) -> np.ndarray:
    """Check and store frame ``index``'s image of ``camera`` (``im``, None when the frame has
    none) at ``rel``; returns the camera's c2w (OpenCV) in the scene's world, from the image's
    own pose where it has one, else the frame's vehicle ``pose``."""
    name = camera.name
    if im is None or not len(im.image):
        raise SceneError(f"frame {index} has no image for camera {name}",
                         scene_id=scene_id, path=where,
                         fix="drop the camera with ingest.cameras or use a complete segment")
    image_pose = (transform_of(im.pose, scene_id=scene_id, where=where,
                               what=f"frame {index} camera {name} image pose")
                  if im.pose is not None else pose)
    pixels = decode_jpeg(im.image, scene_id=scene_id, where=f"{where} camera {name}")
    check_size(pixels, calib.width, calib.height, scene_id=scene_id,
               where=f"{where} camera {name}", what=f"camera {name} image")
    intr = list(calib.intrinsic) + [0.0] * 9
    store_image(out_dir, rel, pixels, K=camera.K(), dist=intr[4:9], quality=quality,
                original=im.image)
    extrinsic = transform_of(calib.extrinsic, scene_id=scene_id, where=where,
                             what=f"camera {name} extrinsic")
    return world_from_global @ image_pose @ extrinsic @ OPENCV_TO_FLU


def _camera(name: str, calib, *, scene_id: str, where) -> Camera:
    intr = list(calib.intrinsic)
    if len(intr) < 4:
        raise SceneError(f"camera {name} calibration has {len(intr)} intrinsics, expected 9 "
                         f"(f_u, f_v, c_u, c_v, k1, k2, p1, p2, k3)", scene_id=scene_id,
                         path=where, fix="the segment is incomplete; re-download it")
    if calib.width <= 0 or calib.height <= 0:
        raise SceneError(f"camera {name} calibration has no image size", scene_id=scene_id,
                         path=where, fix="the segment is incomplete; re-download it")
    extrinsic = transform_of(calib.extrinsic, scene_id=scene_id, where=where,
                             what=f"camera {name} extrinsic")
    return Camera(name=name, width=int(calib.width), height=int(calib.height),
                  fx=float(intr[0]), fy=float(intr[1]), cx=float(intr[2]), cy=float(intr[3]),
                  cam2ego=extrinsic @ OPENCV_TO_FLU)
