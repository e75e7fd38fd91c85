"""Write a scene with known answers in the real log formats, so every ingest path is tested end to end.

Sources: a ``SyntheticStreet`` (rendered here, exact) or a canonical ``Scene`` (its images read
back). Writers:

- ``export_waymo``: one Waymo perception segment (TFRecord of ``Frame`` protos), JPEG images,
  optional lens distortion and a TOP LiDAR range image (zlib MatrixFloat + per-pixel poses);
- ``export_nuscenes``: nuScenes v1.0 tables (scene, sample, sample_data, ego_pose,
  calibrated_sensor, sensor, log, ...) with keyframes and sweeps, images, LIDAR_TOP .pcd.bin;
- ``export_drivestudio``: a DriveStudio processed scene folder, Waymo or nuScenes flavour;
- ``export_video``: one camera as a plain MP4, nothing but pixels (a dashcam).

The source's actors go along: Waymo ``laser_labels``, nuScenes ``sample_annotation`` (keyframes
only, grouped by ``instance``), DriveStudio ``instances/``.

Poses are written in a "global" frame ``GLOBAL @ scene world`` (far from the origin and rotated)
so that a reader that forgets to re-anchor the world at the first ego pose fails the tests.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import functools
import hashlib
import json
import shutil
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Callable

import numpy as np

from paradrive import geometry
from paradrive.actors import Actor, first_frames
from paradrive.ingest import waymo_proto as wp
from paradrive.ingest.common import OPENCV_TO_FLU, encode_jpeg, transform_points
from paradrive.ingest.protowire import encode
from paradrive.ingest.tfrecord import write_records
from paradrive.ingest.undistort import distort_image, distortion_is_zero
from paradrive.io import atomic_path, write_bytes
from paradrive.scene import Camera, Scene, write_image
from paradrive.uri import make_uri

if TYPE_CHECKING:
    from paradrive.contracts.params import IngestParams

# global-from-world of exported logs: 30 deg yaw, a small roll, km-scale offsets
GLOBAL = geometry.make_pose(
    geometry.rotation_about("z", 0.5236) @ geometry.rotation_about("x", 0.01),
    [1234.5, -678.25, 12.75])

NUSCENES_CHANNELS = {"front": "CAM_FRONT", "front_left": "CAM_FRONT_LEFT",
                     "front_right": "CAM_FRONT_RIGHT", "back": "CAM_BACK",
                     "back_left": "CAM_BACK_LEFT", "back_right": "CAM_BACK_RIGHT"}
# DriveStudio camera ids per flavour
DRIVESTUDIO_WAYMO_IDS = {"front": 0, "front_left": 1, "front_right": 2, "side_left": 3,
                         "side_right": 4}
DRIVESTUDIO_NUSCENES_IDS = {"front": 0, "front_left": 1, "front_right": 2, "back_left": 3,
                            "back_right": 4, "back": 5}


# --------------------------------------------------------------------------- sources

@dataclass
class LogSource:
    """What a log holds, in the scene world: the truth exporters write and tests compare with."""

    name: str
    fps: float
    cameras: dict[str, Camera]
    ego2world: np.ndarray                 # (F, 4, 4)
    timestamps_us: np.ndarray             # (F,)
    c2w: dict[str, np.ndarray]            # camera -> (F, 4, 4), OpenCV
    image: Callable[[int, str], np.ndarray]
    sky: Callable[[int, str], np.ndarray | None] = lambda i, cam: None
    lidar: Callable[[int], np.ndarray | None] = lambda i: None
    lidar_origin: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.95]))
    actors: list[Actor] = field(default_factory=list)

    @property
    def frames(self) -> int:
        return len(self.ego2world)


def source_from_street(street, cameras=None, frames: int | None = None) -> LogSource:
    """A LogSource that renders ``street`` (all frames of a camera at its first use)."""
    names = list(cameras or street.cameras)
    n = street.frames if frames is None else min(frames, street.frames)
    cams = {c: Camera(name=c, width=s.width, height=s.height, fx=s.fx, fy=s.fy, cx=s.cx, cy=s.cy,
                      cam2ego=np.asarray(s.cam2ego, dtype=np.float64))
            for c, s in street.cameras.items() if c in names}
    c2w = {c: street.c2w(c)[:n] for c in names}
    cache: dict[str, dict] = {}

    def views(cam):
        if cam not in cache:
            spec = street.cameras[cam]
            cache[cam] = street.render(c2w[cam], spec.K(), spec.width, spec.height,
                                       frames=np.arange(n))
        return cache[cam]

    origin = np.array([0.0, 0.0, 1.95])
    try:
        from paradrive.synthetic import street as street_module

        origin = np.array([0.0, 0.0, float(street_module.LIDAR_HEIGHT)])
    except (ImportError, AttributeError):
        pass
    return LogSource(
        name=f"{street.name}-s{street.seed}", fps=float(street.fps), cameras=cams,
        ego2world=street.ego2world()[:n], timestamps_us=street.timestamps_us()[:n], c2w=c2w,
        image=lambda i, cam: views(cam)["rgb"][i],
        sky=lambda i, cam: views(cam)["sky"][i],
        lidar=functools.lru_cache(maxsize=None)(
            lambda i: np.asarray(street.lidar_points(i), dtype=np.float64)),
        lidar_origin=origin, actors=first_frames(street.actors(), n))


def source_from_scene(scene: Scene, cameras=None, frames: int | None = None) -> LogSource:
    """A LogSource reading a canonical scene's files."""
    names = list(cameras or scene.cameras)
    n = len(scene.frames) if frames is None else min(frames, len(scene.frames))
    root = scene._require_root()

    def lidar(i):
        path = root / "lidar" / f"{scene.frames[i].index:06d}.npy"
        return np.load(path).astype(np.float64) if path.is_file() else None

    return LogSource(
        name=scene.scene_id, fps=scene.fps, cameras={c: scene.cameras[c] for c in names},
        ego2world=scene.ego2world()[:n], timestamps_us=scene.timestamps_us()[:n],
        c2w={c: scene.c2w(c)[:n] for c in names},
        image=lambda i, cam: scene.load_image(i, cam),
        sky=lambda i, cam: scene.sky_mask(i, cam), lidar=lidar,
        actors=first_frames(scene.actors, n))


def as_source(street_or_scene, cameras=None, frames=None) -> LogSource:
    if isinstance(street_or_scene, LogSource):
        return street_or_scene
    if isinstance(street_or_scene, Scene):
        return source_from_scene(street_or_scene, cameras, frames)
    return source_from_street(street_or_scene, cameras, frames)


def _dist_for(distortion, cam: str):
    if distortion is None:
        return (0.0,) * 5
    if isinstance(distortion, dict):
        return tuple(float(d) for d in distortion.get(cam, (0.0,) * 5))
    return tuple(float(d) for d in distortion)


def _token(*parts) -> str:
    return hashlib.md5("/".join(map(str, parts)).encode()).hexdigest()


def _label_name(actor: Actor) -> str:
    """The log's id of an actor: its id without the ``synthetic:`` prefix."""
    return actor.id.split(":", 1)[-1]


# --------------------------------------------------------------------------- Waymo

WAYMO_LABEL_TYPES = {"vehicle": 1, "pedestrian": 2, "cyclist": 4, "other": 0}


def waymo_labels(actors: list[Actor], i: int, ego2world: np.ndarray) -> list[dict]:
    """Frame ``i``'s laser_labels: each actor's box in that frame's vehicle frame."""
    labels = []
    for a in actors:
        pose = a.pose_at(i)
        if pose is None:
            continue
        box = geometry.invert(ego2world) @ pose
        labels.append({"box": {"center_x": box[0, 3], "center_y": box[1, 3], "center_z": box[2, 3],
                               "length": a.size[0], "width": a.size[1], "height": a.size[2],
                               "heading": float(np.arctan2(box[1, 0], box[0, 0]))},
                       "type": WAYMO_LABEL_TYPES[a.cls], "id": _label_name(a)})
    return labels


def rotation_to_euler(rot: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) with R = Rz(yaw) Ry(pitch) Rx(roll)."""
    yaw = np.arctan2(rot[1, 0], rot[0, 0])
    pitch = -np.arcsin(np.clip(rot[2, 0], -1.0, 1.0))
    roll = np.arctan2(rot[2, 1], rot[2, 2])
    return float(roll), float(pitch), float(yaw)


def _matrix_float(values: np.ndarray) -> bytes:
    values = np.asarray(values, dtype=np.float32)
    payload = encode(wp.MatrixFloat, {"data": values.reshape(-1).tolist(),
                                      "shape": {"dims": list(values.shape)}})
    return zlib.compress(payload)


def build_range_image(points_vehicle: np.ndarray, extrinsic: np.ndarray, height: int, width: int,
                      incl_min: float, incl_max: float) -> np.ndarray:
    """Bin vehicle-frame points into a Waymo-layout range image (H, W, 4), nearest return wins.

    Row 0 is the highest inclination (uniform between min and max); column azimuths follow
    Waymo's convention (see waymo.range_image_points).
    """
    sensor = transform_points(geometry.invert(extrinsic), points_vehicle)
    rng = np.linalg.norm(sensor, axis=1)
    ok = rng > 1e-6
    sensor, rng = sensor[ok], rng[ok]
    incl = np.arcsin(np.clip(sensor[:, 2] / rng, -1, 1))
    az = np.arctan2(sensor[:, 1], sensor[:, 0])
    az_correction = np.arctan2(extrinsic[1, 0], extrinsic[0, 0])
    # azimuth = (ratio * 2 - 1) * pi - az_correction, ratio = (W - col - 0.5) / W
    ratio = ((az + az_correction) / np.pi + 1.0) / 2.0
    col = np.mod(np.rint(width - 0.5 - ratio * width), width).astype(np.int64)
    step = (incl_max - incl_min) / height
    row_from_bottom = np.floor((incl - incl_min) / step).astype(np.int64)
    keep = (row_from_bottom >= 0) & (row_from_bottom < height)
    row = height - 1 - row_from_bottom[keep]
    col, rng = col[keep], rng[keep]
    image = np.zeros((height, width, 4), dtype=np.float32)
    image[..., 0] = -1.0
    order = np.argsort(-rng)  # farthest first, so the nearest return is written last
    image[row[order], col[order], 0] = rng[order]
    image[..., 3] = -1.0
    return image


def export_waymo(street_or_scene, path: str | Path, *, cameras=None, frames: int | None = None,
                 segment: str | None = None, distortion=None, lidar: bool = True,
                 jpeg_quality: int = 95, lidar_size: tuple[int, int] = (64, 2048),
                 global_from_world: np.ndarray = GLOBAL) -> Path:
    """Write a Waymo perception segment (``path``, a .tfrecord) of the source's frames.

    distortion: None, (k1, k2, p1, p2, k3) for every camera, or {camera: (...)}; images are then
    recorded through that lens. lidar: write the TOP laser (first return) as a range image with
    per-pixel vehicle poses, when the source has LiDAR points.
    """
    src = as_source(street_or_scene, cameras, frames)
    path = Path(path)
    name = segment or path.stem
    unknown = [c for c in src.cameras if c.upper() not in wp.CAMERA_IDS]
    if unknown:
        raise ValueError(f"cameras {unknown} have no Waymo CameraName; use front, front_left, "
                         f"front_right, side_left, side_right")
    calibs = []
    for cam, c in src.cameras.items():
        dist = _dist_for(distortion, cam)
        calibs.append({"name": wp.CAMERA_IDS[cam.upper()],
                       "intrinsic": [c.fx, c.fy, c.cx, c.cy, *dist],
                       "extrinsic": {"transform": geometry.as_floats(c.cam2ego @ geometry.invert(OPENCV_TO_FLU))},
                       "width": c.width, "height": c.height, "rolling_shutter_direction": 2})
    h, w = lidar_size
    lidar_extrinsic = geometry.make_pose(geometry.rotation_about("z", 0.0123), src.lidar_origin)
    incl_min, incl_max = np.deg2rad(-26.0), np.deg2rad(6.0)
    has_lidar = lidar and src.lidar(0) is not None
    context = {"name": name, "camera_calibrations": calibs,
               "stats": {"time_of_day": "Day", "location": "location_synthetic", "weather": "sunny"}}
    if has_lidar:
        context["laser_calibrations"] = [{
            "name": wp.LASER_IDS["TOP"], "beam_inclination_min": float(incl_min),
            "beam_inclination_max": float(incl_max), "extrinsic": {"transform": geometry.as_floats(lidar_extrinsic)}}]

    def records():
        for i in range(src.frames):
            ego_global = global_from_world @ src.ego2world[i]
            images = []
            for cam, c in src.cameras.items():
                dist = _dist_for(distortion, cam)
                pixels = distort_image(src.image(i, cam), c.K(), dist)
                image_pose = global_from_world @ src.c2w[cam][i] @ geometry.invert(c.cam2ego)
                images.append({"name": wp.CAMERA_IDS[cam.upper()],
                                "image": encode_jpeg(pixels, jpeg_quality),
                                "pose": {"transform": geometry.as_floats(image_pose)},
                                "velocity": {"v_x": 0.0, "v_y": 0.0, "v_z": 0.0},
                                "pose_timestamp": src.timestamps_us[i] / 1e6,
                                "shutter": 0.004})
            frame = {"context": context, "timestamp_micros": int(src.timestamps_us[i]),
                     "pose": {"transform": geometry.as_floats(ego_global)}, "images": images,
                     "laser_labels": waymo_labels(src.actors, i, src.ego2world[i])}
            if has_lidar:
                pts_vehicle = transform_points(geometry.invert(src.ego2world[i]), src.lidar(i))
                ri = build_range_image(pts_vehicle, lidar_extrinsic, h, w, incl_min, incl_max)
                roll, pitch, yaw = rotation_to_euler(ego_global[:3, :3])
                pose_image = np.broadcast_to(
                    np.array([roll, pitch, yaw, *ego_global[:3, 3]], dtype=np.float32), (h, w, 6))
                frame["lasers"] = [{"name": wp.LASER_IDS["TOP"], "ri_return1": {
                    "range_image_compressed": _matrix_float(ri),
                    "range_image_pose_compressed": _matrix_float(pose_image)}}]
            yield encode(wp.Frame, frame)

    write_records(path, records())
    return path


# --------------------------------------------------------------------------- nuScenes

def _write_json(path: Path, rows) -> None:
    write_bytes(path, json.dumps(rows, indent=0).encode())


NUSCENES_CATEGORIES = {"vehicle": "vehicle.car", "pedestrian": "human.pedestrian.adult",
                       "cyclist": "vehicle.bicycle", "other": "animal"}


def nuscenes_annotations(actors: list[Actor], key_idx: list[int], sample_tokens: list[str],
                         global_from_world: np.ndarray) -> dict[str, list[dict]]:
    """category, instance and sample_annotation rows: each actor's boxes at the keyframes, in
    the global frame, size as nuScenes writes it (width, length, height)."""
    categories = {cls: {"token": _token("category", name), "name": name, "description": ""}
                  for cls, name in NUSCENES_CATEGORIES.items()}
    instances, annotations = [], []
    for a in actors:
        keyed = [(k, a.pose_at(i)) for k, i in enumerate(key_idx) if a.pose_at(i) is not None]
        if not keyed:
            continue
        tokens = [_token("sample_annotation", a.id, k) for k, _ in keyed]
        for j, (k, pose) in enumerate(keyed):
            box = global_from_world @ pose
            annotations.append({
                "token": tokens[j], "sample_token": sample_tokens[k],
                "instance_token": _label_name(a), "visibility_token": "4", "attribute_tokens": [],
                "translation": geometry.as_floats(box[:3, 3]), "size": [a.size[1], a.size[0], a.size[2]],
                "rotation": geometry.as_floats(geometry.rotation_to_quaternion(box[:3, :3])),
                "prev": tokens[j - 1] if j else "", "next": tokens[j + 1] if j + 1 < len(tokens) else "",
                "num_lidar_pts": 10, "num_radar_pts": 0})
        instances.append({"token": _label_name(a), "category_token": categories[a.cls]["token"],
                          "nbr_annotations": len(tokens), "first_annotation_token": tokens[0],
                          "last_annotation_token": tokens[-1]})
    return {"category": list(categories.values()), "instance": instances,
            "sample_annotation": annotations}


def _nuscenes_file(target: Path, src, key: str, i: int, lidar2world: np.ndarray,
                   image_format: str, jpeg_quality: int) -> tuple[int, int]:
    """Write frame ``i`` of channel ``key`` (a camera image, or the LiDAR sweep as N x 5 in the
    sensor frame); its (width, height), 0 for the LiDAR."""
    if key == "lidar":
        sweep = src.lidar(i)
        assert sweep is not None  # key "lidar" is only listed when the source has sweeps
        pts = transform_points(geometry.invert(lidar2world), sweep)
        cloud = np.zeros((len(pts), 5), dtype=np.float32)
        cloud[:, :3] = pts
        write_bytes(target, cloud.tobytes())
        return 0, 0
    pixels = src.image(i, key)
    if image_format == "jpg":
        write_bytes(target, encode_jpeg(pixels, jpeg_quality))
    else:
        write_image(target, pixels)
    return src.cameras[key].width, src.cameras[key].height


def export_nuscenes(street_or_scene, dataroot: str | Path, *, cameras=None,
                    frames: int | None = None, version: str = "v1.0-mini",
                    scene_name: str = "scene-0001", keyframe_every: int = 6,
                    image_format: str = "jpg", jpeg_quality: int = 95, lidar: bool = True,
                    time_origin_us: int = 1_531_883_530_000_000,
                    global_from_world: np.ndarray = GLOBAL) -> Path:
    """Write nuScenes v1.0 tables under ``dataroot/version`` plus ``samples/`` and ``sweeps/``.

    Every ``keyframe_every``-th camera frame is a keyframe (a sample); the others are sweeps,
    chained by prev/next per channel. Each image has its own ego pose (from the source's c2w).
    ``image_format`` 'png' writes lossless images (the real dataset has JPEGs).
    """
    src = as_source(street_or_scene, cameras, frames)
    root = Path(dataroot)
    unknown = [c for c in src.cameras if c not in NUSCENES_CHANNELS]
    if unknown:
        raise ValueError(f"cameras {unknown} have no nuScenes channel; use "
                         f"{', '.join(NUSCENES_CHANNELS)}")
    log_token = _token("log", scene_name)
    scene_token = _token("scene", scene_name)
    log = _NuscenesLog(src, root, scene_name, [int(time_origin_us + t) for t in src.timestamps_us],
                       keyframe_every, image_format, jpeg_quality, global_from_world)
    samples = [{"token": tok, "timestamp": log.stamps[i],
                "prev": log.sample_tokens[k - 1] if k else "",
                "next": log.sample_tokens[k + 1] if k + 1 < len(log.key_idx) else "",
                "scene_token": scene_token} for k, (i, tok) in enumerate(zip(log.key_idx, log.sample_tokens))]
    channels = {cam: NUSCENES_CHANNELS[cam] for cam in src.cameras}
    if lidar and src.lidar(0) is not None:
        channels["lidar"] = "LIDAR_TOP"
    sensors: dict[str, list[dict]] = {"sensor": [], "calibrated_sensor": [], "ego_pose": [], "sample_data": []}
    for key, channel in channels.items():
        for table, rows in log.channel(key, channel).items():
            sensors[table] += rows
    tables: dict[str, list[dict]] = {
        "log": [{"token": log_token, "logfile": f"n000-{scene_name}", "vehicle": "n000",
                 "date_captured": "2018-07-18", "location": "synthetic"}],
        "scene": [{"token": scene_token, "log_token": log_token, "nbr_samples": len(samples),
                   "first_sample_token": log.sample_tokens[0], "last_sample_token": log.sample_tokens[-1],
                   "name": scene_name, "description": f"synthetic {src.name}"}],
        "sample": samples, "sample_data": sensors["sample_data"], "ego_pose": sensors["ego_pose"],
        "calibrated_sensor": sensors["calibrated_sensor"], "sensor": sensors["sensor"],
        "attribute": [], "visibility": [], "map": [],
        **nuscenes_annotations(src.actors, log.key_idx, log.sample_tokens, global_from_world),
    }
    for table, rows in tables.items():
        _write_json(root / version / f"{table}.json", rows)
    return root


@dataclass
class _NuscenesLog:
    """What every channel of an exported nuScenes log shares: its frames' timestamps (us), its
    keyframes and their sample tokens, where and how its files are written."""

    src: LogSource
    root: Path
    scene_name: str
    stamps: list[int]
    keyframe_every: int
    image_format: str
    jpeg_quality: int
    global_from_world: np.ndarray
    key_idx: list[int] = field(init=False)
    sample_tokens: list[str] = field(init=False)

    def __post_init__(self) -> None:
        self.key_idx = list(range(0, self.src.frames, self.keyframe_every))
        self.sample_tokens = [_token("sample", self.scene_name, i) for i in self.key_idx]

    def sample_of(self, i: int) -> str:
        """The sample of frame ``i``: its own keyframe's, or a sweep's next keyframe (the last
        one at the end)."""
        k = min(-(-i // self.keyframe_every), len(self.key_idx) - 1)
        return self.sample_tokens[k]

    def channel(self, key: str, channel: str) -> dict[str, list[dict]]:
        """Write every frame of one channel (a camera, or ``lidar``); its sensor, calibrated
        sensor, ego pose and sample data rows."""
        src, scene_name = self.src, self.scene_name
        lidar_cam2ego = geometry.make_pose(geometry.rotation_about("z", -np.pi / 2), src.lidar_origin)
        sensor_token = _token("sensor", channel)
        cs_token = _token("calibrated_sensor", scene_name, channel)
        pose, intrinsic = (lidar_cam2ego, []) if key == "lidar" else \
            (src.cameras[key].cam2ego, src.cameras[key].K().tolist())
        rows: dict[str, list[dict]] = {
            "sensor": [{"token": sensor_token, "channel": channel,
                        "modality": "lidar" if key == "lidar" else "camera"}],
            "calibrated_sensor": [{"token": cs_token, "sensor_token": sensor_token,
                                   "translation": geometry.as_floats(pose[:3, 3]),
                                   "rotation": geometry.as_floats(geometry.rotation_to_quaternion(pose[:3, :3])),
                                   "camera_intrinsic": intrinsic}],
            "ego_pose": [], "sample_data": []}
        tokens = [_token("sample_data", scene_name, channel, i) for i in range(src.frames)]
        for i in range(src.frames):
            keyframe = i % self.keyframe_every == 0
            folder = "samples" if keyframe else "sweeps"
            if key == "lidar":
                ego = src.ego2world[i]
                ext, fmt = "pcd.bin", "pcd"
            else:
                ego = src.c2w[key][i] @ geometry.invert(src.cameras[key].cam2ego)
                ext, fmt = self.image_format, self.image_format
            ego_global = self.global_from_world @ ego
            ego_token = _token("ego_pose", scene_name, channel, i)
            rows["ego_pose"].append({
                "token": ego_token, "timestamp": self.stamps[i],
                "rotation": geometry.as_floats(geometry.rotation_to_quaternion(ego_global[:3, :3])),
                "translation": geometry.as_floats(ego_global[:3, 3])})
            filename = f"{folder}/{channel}/n000-{scene_name}__{channel}__{self.stamps[i]}.{ext}"
            width, height = _nuscenes_file(self.root / filename, src, key, i, ego @ lidar_cam2ego,
                                           self.image_format, self.jpeg_quality)
            rows["sample_data"].append({
                "token": tokens[i], "sample_token": self.sample_tokens[i // self.keyframe_every] if keyframe
                else self.sample_of(i), "ego_pose_token": ego_token, "calibrated_sensor_token": cs_token,
                "timestamp": self.stamps[i], "fileformat": fmt, "is_key_frame": keyframe,
                "height": height, "width": width, "filename": filename,
                "prev": tokens[i - 1] if i else "", "next": tokens[i + 1] if i + 1 < src.frames else ""})
        return rows


# --------------------------------------------------------------------------- DriveStudio

DRIVESTUDIO_CLASS_NAMES = {"vehicle": "Vehicle", "pedestrian": "Pedestrian", "cyclist": "Cyclist"}


def drivestudio_instances(actors: list[Actor], frames: int, global_from_world: np.ndarray,
                          flavour: str) -> tuple[dict, dict]:
    """(instances_info, frame_instances) as DriveStudio's preprocessors write them: instances
    numbered 0.., each with per-frame obj_to_world (global) and box_size (length, width, height)."""
    info: dict[str, dict] = {}
    per_frame: dict[str, list[int]] = {str(i): [] for i in range(frames)}
    names = DRIVESTUDIO_CLASS_NAMES if flavour == "waymo" else NUSCENES_CATEGORIES
    for a in actors:
        if a.cls not in names:
            continue
        number = len(info)
        info[str(number)] = {"id": _label_name(a), "class_name": names[a.cls], "frame_annotations": {
            "frame_idx": [int(f) for f in a.frames],
            "obj_to_world": [(global_from_world @ p).tolist() for p in a.box2world],
            "box_size": [[float(v) for v in a.size]] * len(a.frames)}}
        for f in a.frames:
            per_frame[str(int(f))].append(number)
    return info, per_frame

def _drivestudio_image(tmp: Path, src, i: int, cam: str, c, cid, flavour: str,
                       global_from_world: np.ndarray, dist, sky_masks: bool,
                       jpeg_quality: int) -> None:
    """Frame ``i`` of camera ``cam``: the (distorted) JPEG, its pose (nuScenes flavour), its sky mask."""
    t = f"{i:03d}"
    pixels = distort_image(src.image(i, cam), c.K(), dist)
    (tmp / "images" / f"{t}_{cid}.jpg").write_bytes(encode_jpeg(pixels, jpeg_quality))
    if flavour == "nuscenes":
        np.savetxt(tmp / "extrinsics" / f"{t}_{cid}.txt", global_from_world @ src.c2w[cam][i])
    sky = src.sky(i, cam) if sky_masks else None
    if sky is not None:
        mask = (np.asarray(sky, dtype=bool).astype(np.uint8) * 255)
        if not distortion_is_zero(dist):
            mask = distort_image(mask[..., None], c.K(), dist)[..., 0]
            mask = np.where(mask > 127, 255, 0).astype(np.uint8)
        write_image(tmp / "sky_masks" / f"{t}_{cid}.png", mask)


def _drivestudio_lidar(tmp: Path, src, i: int, flavour: str, lidar2ego: np.ndarray,
                       global_from_world: np.ndarray) -> None:
    """Frame ``i``'s sweep: N x 14 in the vehicle frame (Waymo flavour) or N x 4 in the LiDAR
    frame with its pose (nuScenes flavour)."""
    t = f"{i:03d}"
    pts_world = src.lidar(i)
    if flavour == "waymo":
        pts = transform_points(geometry.invert(src.ego2world[i]), pts_world)
        rows = np.zeros((len(pts), 14), dtype=np.float32)
        rows[:, 0:3] = src.lidar_origin
        rows[:, 3:6] = pts
        rows[:, 9] = -1.0
        rows[:, 13] = 0.0  # TOP
    else:
        lidar2world = src.ego2world[i] @ lidar2ego
        pts = transform_points(geometry.invert(lidar2world), pts_world)
        rows = np.zeros((len(pts), 4), dtype=np.float32)
        rows[:, :3] = pts
        np.savetxt(tmp / "lidar_pose" / f"{t}.txt", global_from_world @ lidar2world)
    rows.tofile(tmp / "lidar" / f"{t}.bin")


def export_drivestudio(street_or_scene, folder: str | Path, *, flavour: str = "waymo",
                       cameras=None, frames: int | None = None, distortion=None,
                       sky_masks: bool = True, lidar: bool = True, jpeg_quality: int = 95,
                       global_from_world: np.ndarray = GLOBAL) -> Path:
    """Write one DriveStudio processed scene folder (e.g. ``processed/training/023``).

    Waymo flavour: images/<t:03d>_<cam>.jpg, ego_pose/<t:03d>.txt (vehicle -> global),
    extrinsics/<cam>.txt (camera (x fwd, y left, z up) -> vehicle), intrinsics/<cam>.txt
    (f_u f_v c_u c_v k1 k2 p1 p2 k3), sky_masks/<t:03d>_<cam>.png, lidar/<t:03d>.bin (N x 14
    float32: origin, point (vehicle frame), flow, flow class, ground, intensity, elongation,
    laser id). nuScenes flavour: extrinsics/<t:03d>_<cam>.txt (camera (OpenCV) -> global),
    intrinsics/<cam>.txt (distortion zero), lidar/<t:03d>.bin (N x 4, LiDAR frame) and
    lidar_pose/<t:03d>.txt.
    """
    src = as_source(street_or_scene, cameras, frames)
    if flavour not in ("waymo", "nuscenes"):
        raise ValueError(f"flavour must be 'waymo' or 'nuscenes', got {flavour!r}")
    ids = DRIVESTUDIO_WAYMO_IDS if flavour == "waymo" else DRIVESTUDIO_NUSCENES_IDS
    unknown = [c for c in src.cameras if c not in ids]
    if unknown:
        raise ValueError(f"cameras {unknown} have no DriveStudio {flavour} id; use {', '.join(ids)}")
    folder = Path(folder)
    with atomic_path(folder) as tmp:
        for sub in ("images", "extrinsics", "intrinsics", "sky_masks"):
            (tmp / sub).mkdir(parents=True)
        for cam, c in src.cameras.items():
            cid = ids[cam]
            dist = _dist_for(distortion if flavour == "waymo" else None, cam)
            np.savetxt(tmp / "intrinsics" / f"{cid}.txt", [c.fx, c.fy, c.cx, c.cy, *dist])
            if flavour == "waymo":
                np.savetxt(tmp / "extrinsics" / f"{cid}.txt",
                           c.cam2ego @ geometry.invert(OPENCV_TO_FLU))
        has_lidar = lidar and src.lidar(0) is not None
        if has_lidar:
            (tmp / "lidar").mkdir()
            if flavour == "nuscenes":
                (tmp / "lidar_pose").mkdir()
        if flavour == "waymo":
            (tmp / "ego_pose").mkdir()
        lidar2ego = geometry.translation(*src.lidar_origin)
        for i in range(src.frames):
            if flavour == "waymo":
                np.savetxt(tmp / "ego_pose" / f"{i:03d}.txt", global_from_world @ src.ego2world[i])
            for cam, c in src.cameras.items():
                _drivestudio_image(tmp, src, i, cam, c, ids[cam], flavour, global_from_world,
                                   _dist_for(distortion if flavour == "waymo" else None, cam),
                                   sky_masks, jpeg_quality)
            if has_lidar:
                _drivestudio_lidar(tmp, src, i, flavour, lidar2ego, global_from_world)
        if not sky_masks:
            shutil.rmtree(tmp / "sky_masks")
        info, per_frame = drivestudio_instances(src.actors, src.frames, global_from_world, flavour)
        (tmp / "instances").mkdir()
        (tmp / "instances" / "instances_info.json").write_text(json.dumps(info))
        (tmp / "instances" / "frame_instances.json").write_text(json.dumps(per_frame))
    return folder


# --------------------------------------------------------------------------- command line

# what each format's log is ingested as (DriveStudio folders are written in the Waymo flavour),
# --------------------------------------------------------------------------- a plain video

MIN_VIDEO_WIDTH = 320

def export_video(street_or_scene, path: str | Path, *, camera: str = "front",
                 frames: int | None = None, crf: int = 18) -> dict:
    """Write one camera of the source as a plain H.264 MP4 (``path``): no poses, calibration or
    LiDAR, as a dashcam records. Returns the camera's intrinsics and mount height (m above the
    ego origin, on the road) that the ``video:`` URI may state, and the encoder's summary."""
    from paradrive.video import encode_video

    src = as_source(street_or_scene, [camera], frames)
    c = src.cameras[camera]
    summary = encode_video(path, (src.image(i, camera) for i in range(src.frames)), src.fps,
                           crf=crf)
    return {**summary, "fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy,
            "height_m": float(c.cam2ego[2, 3]), "fps": src.fps}


def video_uri(path: Path, info: dict, truth: str, *, with_intrinsics: bool) -> str:
    """The ``video:`` URI that ingests a file of :func:`export_video`: its frame rate, the mount
    height, the synthetic URI it shows (``truth``, for ``paradrive eval``) and, when asked, the
    intrinsics (otherwise SfM estimates them)."""
    from urllib.parse import quote

    query = {"fps": f"{info['fps']:g}", "height_m": f"{info['height_m']:g}"}
    if with_intrinsics:  # in OpenCV's convention, as a calibration reports them: centres at 0
        query.update({"fx": f"{info['fx']:.6f}", "fy": f"{info['fy']:.6f}",
                      "cx": f"{info['cx'] - 0.5:.6f}", "cy": f"{info['cy'] - 0.5:.6f}"})
    query["truth"] = truth
    return make_uri("video", str(path), "&".join(f"{k}={quote(v, safe=':/')}" for k, v in query.items()))


# and the cameras the format can hold
EXPORT_DATASETS = {"waymo": "waymo", "nuscenes": "nuscenes", "drivestudio": "waymo"}
EXPORT_CAMERAS = {"waymo": tuple(n.lower() for n in wp.CAMERA_IDS if n != "UNKNOWN"),
                  "nuscenes": tuple(NUSCENES_CHANNELS),
                  "drivestudio": tuple(DRIVESTUDIO_WAYMO_IDS)}


def export_cameras(fmt: str, ingest_params: IngestParams, scene_id: str) -> list[str]:
    """The rig cameras a log in format ``fmt`` carries: those its ingest asks for with
    ``ingest_params`` (``auto``: the dataset's fit set), or, for every camera, all the format holds."""
    from paradrive.ingest import requested_cameras
    from paradrive.synthetic.street import CAMERA_NAMES

    wanted = requested_cameras(ingest_params, EXPORT_DATASETS[fmt], scene_id=scene_id)
    return wanted if wanted is not None else [c for c in CAMERA_NAMES if c in EXPORT_CAMERAS[fmt]]


def _video_params(uri, ingest_params: IngestParams) -> IngestParams:
    """The street's front camera, at least :data:`MIN_VIDEO_WIDTH` wide unless the URI sets the
    size: structure from motion finds too few road points on the smoke profile's 160x96 frames
    to measure the camera's height, and the printed URI must build with the profile it came from."""
    update: dict = {"cameras": ["front"]}
    width, height = ingest_params.synthetic_width, ingest_params.synthetic_height
    if "width" not in uri.query and "height" not in uri.query and width < MIN_VIDEO_WIDTH:
        factor = -(-MIN_VIDEO_WIDTH // width)
        update.update(synthetic_width=width * factor, synthetic_height=height * factor)
    return ingest_params.model_copy(update=update)


def export_scene(scene_uri: str, fmt: str, out: str | Path, ingest_params: IngestParams, *,
                 with_intrinsics: bool = True) -> str:
    """Write the synthetic scene ``scene_uri`` in format ``fmt`` under ``out``; returns its URI.

    The log carries the cameras that ingesting it with ``ingest_params`` keeps (``export_cameras``);
    a ``video`` is the front camera alone, its URI with the intrinsics when ``with_intrinsics``.
    """
    from paradrive.ingest.synthetic import street_from_uri
    from paradrive.uri import parse_uri

    uri = parse_uri(scene_uri)
    if uri.kind != "synthetic":
        raise ValueError(f"export writes synthetic scenes only, got {scene_uri!r}")
    if fmt == "video":
        street = street_from_uri(uri, _video_params(uri, ingest_params))
        path = Path(out).resolve() / f"{uri.scene_id}.mp4"
        info = export_video(street, path)
        truth = (f"synthetic:{street.name}?seed={street.seed}&frames={street.frames}"
                 f"&width={street.width}&height={street.height}&curvature={street.curvature:g}")
        return video_uri(path, info, truth, with_intrinsics=with_intrinsics)
    if fmt not in EXPORT_DATASETS:
        raise ValueError(f"unknown format {fmt!r}; use waymo, nuscenes, drivestudio or video")
    cameras = export_cameras(fmt, ingest_params, uri.scene_id)
    street = street_from_uri(uri, ingest_params.model_copy(update={"cameras": cameras}))
    out = Path(out).resolve()
    name = uri.scene_id
    if fmt == "waymo":
        path = export_waymo(street, out / f"segment-{name}_with_camera_labels.tfrecord",
                            segment=name)
        return make_uri("waymo", str(path))
    if fmt == "nuscenes":
        export_nuscenes(street, out, scene_name=name)
        return make_uri("nuscenes", str(out), "version=v1.0-mini", name)
    return make_uri("drivestudio", str(export_drivestudio(street, out / name)))
