"""``nuscenes:<dataroot>?version=v1.0-mini#scene-0061``: a nuScenes v1.0 scene, read from its JSON tables.

Tables (``<dataroot>/<version>/<table>.json``): scene, sample, sample_data, ego_pose,
calibrated_sensor, sensor (log when present), looked up through a one-time index of the
version's tables so that a scene reads only its own rows (:mod:`.nuscenes_tables`).
A camera's frames are its full sample_data chain (keyframes and sweeps, ~12 Hz), followed by
``next`` from the sample_data of the scene's first sample while it stays in the scene. The
first camera asked for is the frame clock; the other cameras take their image nearest in time.
Each image has its own ego pose, so::

    c2w = inv(ego_0) · ego_pose(image) · calibrated_sensor(camera)

with ego_0 the first frame's ego pose (world = first ego pose). nuScenes camera frames are
already OpenCV-style and its images already undistorted; quaternions are (w, x, y, z).
With ``lidar`` on, the LIDAR_TOP sweep nearest each frame (``.pcd.bin``, float32 x y z
intensity ring) becomes world points.
Actors: ``sample_annotation`` rows grouped by ``instance`` (category from ``category.json``),
boxes at the 2 Hz keyframes in the global frame with ``size`` = width, length, height;
each track is interpolated to the camera frames between its first and last annotation
(linear position, slerp rotation), never extrapolated.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from pathlib import Path

import numpy as np

from paradrive import actors as act
from paradrive import geometry
from paradrive.errors import SceneError
from paradrive.ingest import select_cameras
from paradrive.ingest.common import (
    check_increasing, check_size, checked_pose, decode_jpeg, fps_from, save_points,
    store_image, transform_points,
)
from paradrive.ingest.nuscenes_tables import Tables, open_tables
from paradrive.scene import Camera, Frame, FrameCamera, Scene
from paradrive.uri import SceneURI

if TYPE_CHECKING:
    from paradrive.contracts.params import IngestParams

CHANNEL_TO_CAMERA = {"CAM_FRONT": "front", "CAM_FRONT_LEFT": "front_left",
                     "CAM_FRONT_RIGHT": "front_right", "CAM_BACK": "back",
                     "CAM_BACK_LEFT": "back_left", "CAM_BACK_RIGHT": "back_right"}
CAMERA_TO_CHANNEL = {v: k for k, v in CHANNEL_TO_CAMERA.items()}
FPS = 12.0


def find_version(root: Path, uri: SceneURI, scene_id: str) -> str:
    if "version" in uri.query:
        return uri.query["version"]
    found = sorted(p.name for p in root.glob("v1.0-*") if p.is_dir())
    if len(found) == 1:
        return found[0]
    raise SceneError(f"cannot tell the dataset version (found {found or 'no v1.0-* folder'})",
                     scene_id=scene_id, path=root,
                     fix="add ?version=v1.0-trainval (or v1.0-mini) to the scene URI")


def _get(tables: Tables, table: str, token: str, *, scene_id: str, where, referrer: str) -> dict:
    row = tables.get(table, token)
    if row is None:
        raise SceneError(f"{referrer} refers to {table} {token!r}, which is not in {table}.json",
                         scene_id=scene_id, path=where, fix="the tables are inconsistent; "
                                                            "re-extract the metadata archive")
    return row


def _pose(row: dict, *, scene_id: str, where, what: str) -> np.ndarray:
    try:   # a missing key names itself (nuscenes_tables.Row)
        q = np.asarray(row["rotation"], dtype=np.float64)
        t = np.asarray(row["translation"], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise SceneError(f"{what} lacks rotation/translation ({exc})", scene_id=scene_id,
                         path=where, fix="re-extract the nuScenes metadata archive") from exc
    if q.shape != (4,) or t.shape != (3,) or not (np.isfinite(q).all() and np.isfinite(t).all()):
        problem = "has NaN" if q.shape == (4,) and t.shape == (3,) else "is malformed"
        raise SceneError(f"{what} {problem}", scene_id=scene_id, path=where,
                         fix="fix or drop the record in the log")
    if abs(np.linalg.norm(q) - 1.0) > 1e-3:
        raise SceneError(f"{what} rotation is not a unit quaternion (|q| = {np.linalg.norm(q):.4f})",
                         scene_id=scene_id, path=where, fix="fix the record in the log")
    pose = geometry.make_pose(geometry.quaternion_to_rotation(q), t)
    return checked_pose(pose, scene_id=scene_id, where=where, what=what)


def find_scene(tables: Tables, uri: SceneURI, scene_id: str, where) -> dict:
    scenes = tables.rows("scene")
    if uri.scene:
        hits = [s for s in scenes if s.get("name") == uri.scene or s["token"] == uri.scene]
        if not hits:
            names = ", ".join(sorted(s.get("name", "?") for s in scenes)[:8])
            raise SceneError(f"no scene {uri.scene!r} in scene.json (has {names}...)",
                             scene_id=scene_id, path=where, fix="check the name after '#'")
        return hits[0]
    if len(scenes) == 1:
        return scenes[0]
    raise SceneError(f"scene.json has {len(scenes)} scenes", scene_id=scene_id, path=where,
                     fix="name one with '#scene-0061'")


def channel_of(tables, sd: dict, *, scene_id: str, where) -> str:
    cs = _get(tables, "calibrated_sensor", sd["calibrated_sensor_token"], scene_id=scene_id,
              where=where, referrer=f"sample_data {sd['token']}")
    sensor = _get(tables, "sensor", cs["sensor_token"], scene_id=scene_id, where=where,
                  referrer=f"calibrated_sensor {cs['token']}")
    return sensor["channel"]


def chain(tables, start: dict, scene_samples: set[str], *, scene_id: str, where) -> list[dict]:
    """sample_data rows from ``start`` following ``next`` while they belong to the scene."""
    rows, seen = [], set()
    sd: dict | None = start
    while sd is not None and sd["sample_token"] in scene_samples and sd["token"] not in seen:
        rows.append(sd)
        seen.add(sd["token"])
        nxt = sd.get("next") or ""
        sd = _get(tables, "sample_data", nxt, scene_id=scene_id, where=where,
                  referrer=f"sample_data {sd['token']}") if nxt else None
    return rows


# --------------------------------------------------------------------------- actors

def instance_kind(tables, instance: str) -> tuple[str, bool] | None:
    """(class, rigid) of an instance by its category; None for static categories.

    KeyError (its message naming the table and field) when the class cannot be told."""
    row = tables.get("instance", instance)
    if row is None:
        raise KeyError(f"instance {instance!r} is not in instance.json")
    category = tables.get("category", str(row.get("category_token")))
    if category is None:
        raise KeyError(f"category_token {row.get('category_token')!r} is not in category.json")
    try:
        return act.class_of_nuscenes(category.get("name"))
    except KeyError:
        raise KeyError(f"category {category.get('name')!r} is not a nuScenes category "
                       "(category.json name)") from None


def instance_boxes(rows: list[dict], sample_time: dict[str, int], world_from_global):
    """Keyframe times (K,), box2world (K, 4, 4) and sizes (K, 3) (length, width, height) of one
    instance's annotations, sorted by time; ValueError naming the bad row."""
    outside = [r for r in rows if r["sample_token"] not in sample_time]
    if outside:
        raise ValueError(f"sample_annotation {outside[0]['token']} sample_token "
                         f"{outside[0]['sample_token']!r} is not a sample of this scene")
    rows = sorted(rows, key=lambda r: sample_time[r["sample_token"]])
    times = np.asarray([sample_time[r["sample_token"]] for r in rows], dtype=np.int64)
    if (np.diff(times) == 0).any():
        raise ValueError("two sample_annotation rows in one sample (duplicate instance)")
    poses = [world_from_global @ geometry.make_pose(geometry.quaternion_to_rotation(r["rotation"]),
                                                    r["translation"]) for r in rows]
    sizes = [[r["size"][1], r["size"][0], r["size"][2]] for r in rows]  # w, l, h -> l, w, h
    return times, np.asarray(poses, dtype=np.float64), np.asarray(sizes, dtype=np.float64)


def instance_actor(tables, instance: str, rows: list[dict], sample_time: dict[str, int],
                   stamps: list[int], world_from_global, *, scene_id: str,
                   where) -> act.Actor | None:
    """One instance's track over the camera frames, or None (static, or dropped and logged)."""
    key = f"nuscenes:{instance}"
    try:
        kind = instance_kind(tables, instance)
    except KeyError as exc:
        act.log_dropped(key, str(exc.args[0]), scene_id=scene_id, where=where)
        return None
    if kind is None:
        return None
    try:
        times, poses, sizes = instance_boxes(rows, sample_time, world_from_global)
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        act.log_dropped(key, f"{type(exc).__name__}: {exc}", scene_id=scene_id, where=where)
        return None
    inside, track = act.interpolate_track(times, poses, np.asarray(stamps))
    if not inside.any():
        return None
    return act.actor_from_boxes(key, kind[0], kind[1], np.flatnonzero(inside), track, sizes)


def annotation_actors(tables, samples: list[str], stamps: list[int], world_from_global, *,
                      scene_id: str, meta: Path) -> list[act.Actor]:
    """The actors of the scene's instances, at the frames of ``stamps`` (us)."""
    sample_time = {tok: int(_get(tables, "sample", tok, scene_id=scene_id, where=meta / "sample.json",
                                 referrer="the scene's sample chain")["timestamp"]) for tok in samples}
    by_instance: dict[str, list[dict]] = {}
    for row in tables.annotations_of(samples):  # every row of each instance seen in the scene
        by_instance.setdefault(row.get("instance_token"), []).append(row)
    where = meta / "sample_annotation.json"
    found = [instance_actor(tables, inst, rows, sample_time, stamps, world_from_global,
                            scene_id=scene_id, where=where)
             for inst, rows in by_instance.items()]
    return act.keep_valid([a for a in found if a is not None], range(len(stamps)),
                          scene_id=scene_id, where=where)


def read(uri: SceneURI, out_dir: Path, params: IngestParams, scene_id: str,
         tables: Tables | None = None) -> Scene:
    """The scene of ``uri``, its rows read from ``tables`` (default: through the version's
    table index, see :mod:`paradrive.ingest.nuscenes_tables`)."""
    root = Path(uri.path).expanduser()
    if not root.is_dir():
        raise SceneError("nuScenes dataroot does not exist", scene_id=scene_id, path=root,
                         fix="check the path in the scene URI")
    return _Reader(uri, root, out_dir, params, scene_id, tables).scene()


def _first_sample_data(tables: Tables, first_sample: str, scene_id: str, where: Path) -> dict[str, dict]:
    """The first sample's sample_data per channel: a keyframe if there is one, else the earliest."""
    firsts: dict[str, dict] = {}
    for sd in tables.sample_data_of(first_sample):
        ch = channel_of(tables, sd, scene_id=scene_id, where=where)
        old = firsts.get(ch)
        if old is None or (sd.get("is_key_frame") and not old.get("is_key_frame")) or (
                sd.get("is_key_frame") == old.get("is_key_frame") and sd["timestamp"] < old["timestamp"]):
            firsts[ch] = sd
    return firsts


class _Reader:
    """One scene of a nuScenes dataroot read into a canonical scene, step by step."""

    def __init__(self, uri: SceneURI, root: Path, out_dir: Path, params: IngestParams, scene_id: str,
                 tables: Tables | None = None):
        self.uri, self.root, self.out_dir, self.params, self.scene_id = uri, root, out_dir, params, scene_id
        self.version = find_version(root, uri, scene_id)
        self.meta = meta = root / self.version
        self.tables = tables if tables is not None else open_tables(meta, scene_id)
        self.scene_row = find_scene(self.tables, uri, scene_id, meta / "scene.json")
        self.samples = self.sample_chain()
        self.where_sd = meta / "sample_data.json"
        self.firsts = _first_sample_data(self.tables, self.samples[0], scene_id, self.where_sd)
        available = [CHANNEL_TO_CAMERA[ch] for ch in CHANNEL_TO_CAMERA if ch in self.firsts]
        self.chosen = select_cameras(available, params, "nuscenes", scene_id=scene_id, where=meta)
        self.chains = {cam: chain(self.tables, self.firsts[CAMERA_TO_CHANNEL[cam]],
                                  set(self.samples), scene_id=scene_id, where=self.where_sd)
                       for cam in self.chosen}
        clock = self.chains[self.chosen[0]]
        limit = params.max_frames
        self.clock = clock[:limit] if limit is not None else clock
        self.stamps = [int(sd["timestamp"]) for sd in self.clock]
        check_increasing(self.stamps, scene_id=scene_id, where=self.where_sd,
                         labels=[f"sample_data {sd['token']} (frame {i}, {self.chosen[0]})"
                                 for i, sd in enumerate(self.clock)])
        self.world = geometry.invert(self.ego_of(self.clock[0]))

    def sample_chain(self) -> list[str]:
        """The scene's sample tokens, by walking the sample chain."""
        row = self.scene_row
        samples, token = [], row["first_sample_token"]
        while token:
            sample = _get(self.tables, "sample", token, scene_id=self.scene_id,
                          where=self.meta / "sample.json", referrer=f"scene {row.get('name')}")
            if sample["token"] in samples:
                break
            samples.append(sample["token"])
            token = "" if token == row.get("last_sample_token") else sample.get("next", "")
        return samples

    def ego_of(self, sd: dict) -> np.ndarray:
        row = _get(self.tables, "ego_pose", sd["ego_pose_token"], scene_id=self.scene_id,
                   where=self.where_sd, referrer=f"sample_data {sd['token']}")
        return _pose(row, scene_id=self.scene_id, where=self.meta / "ego_pose.json",
                     what=f"ego_pose {row['token']}")

    def calib_of(self, sd: dict) -> tuple[dict, np.ndarray]:
        row = _get(self.tables, "calibrated_sensor", sd["calibrated_sensor_token"],
                   scene_id=self.scene_id, where=self.where_sd, referrer=f"sample_data {sd['token']}")
        return row, _pose(row, scene_id=self.scene_id, where=self.meta / "calibrated_sensor.json",
                          what=f"calibrated_sensor {row['token']}")

    def camera(self, cam: str) -> Camera:
        sd = self.chains[cam][0]
        row, cam2ego = self.calib_of(sd)
        K = np.asarray(row.get("camera_intrinsic") or [], dtype=np.float64)
        if K.shape != (3, 3):
            raise SceneError(f"calibrated_sensor {row['token']} ({cam}) has no 3x3 camera_intrinsic",
                             scene_id=self.scene_id, path=self.meta / "calibrated_sensor.json",
                             fix="check the calibration tables")
        return Camera(name=cam, width=int(sd.get("width") or 0), height=int(sd.get("height") or 0),
                      fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]),
                      cam2ego=cam2ego)

    def scene(self) -> Scene:
        cameras = {cam: self.camera(cam) for cam in self.chosen}
        chain_stamps = {cam: np.asarray([int(sd["timestamp"]) for sd in self.chains[cam]],
                                        dtype=np.int64) for cam in self.chosen}
        frames = []
        for i, sd_clock in enumerate(self.clock):
            frame = Frame(index=i, timestamp_us=self.stamps[i],
                          ego2world=self.world @ self.ego_of(sd_clock), cameras={})
            for cam in self.chosen:
                sd = sd_clock if cam == self.chosen[0] else self.chains[cam][
                    int(np.argmin(np.abs(chain_stamps[cam] - self.stamps[i])))]
                frame.cameras[cam] = self.image(cameras[cam], sd, i)
            frames.append(frame)
        if self.params.lidar and "LIDAR_TOP" in self.firsts:
            self.lidar()
        row = self.scene_row
        log = self.tables.get("log", str(row.get("log_token"))) or {}
        return Scene(scene_id=self.scene_id, dataset="nuscenes", source=self.uri.text,
                     fps=fps_from(self.stamps, FPS), cameras=cameras, frames=frames,
                     actors=annotation_actors(self.tables, self.samples, self.stamps, self.world,
                                              scene_id=self.scene_id, meta=self.meta),
                     extra={"nuscenes": {"version": self.version, "scene": row.get("name"),
                                         "scene_token": row["token"],
                                         "location": log.get("location")}})

    def image(self, c: Camera, sd: dict, i: int) -> FrameCamera:
        """Store frame ``i`` of camera ``c`` (sample_data ``sd``); its place in the scene."""
        image_path = self.root / sd["filename"]
        if not image_path.is_file():
            raise SceneError(f"image of sample_data {sd['token']} ({c.name}, frame {i}) is missing",
                             scene_id=self.scene_id, path=image_path,
                             fix="download the sweeps/samples archives of this part of the "
                                 "dataset, or drop the camera")
        data = image_path.read_bytes()
        pixels = decode_jpeg(data, scene_id=self.scene_id, where=image_path)
        if c.width == 0:  # older tables leave width/height out
            c.width, c.height = pixels.shape[1], pixels.shape[0]
        check_size(pixels, c.width, c.height, scene_id=self.scene_id, where=image_path,
                   what=f"camera {c.name} image")
        rel = f"images/{c.name}/{i:06d}.{self.params.image_ext}"
        store_image(self.out_dir, rel, pixels, quality=self.params.jpeg_quality,
                    original=data if image_path.suffix.lower() in (".jpg", ".jpeg") else None)
        _, cam2ego = self.calib_of(sd)
        return FrameCamera(image=rel, c2w=self.world @ self.ego_of(sd) @ cam2ego)

    def lidar(self) -> None:
        """World points of the LiDAR sweep nearest each frame (``lidar/<frame>.npy``)."""
        lidar_chain = chain(self.tables, self.firsts["LIDAR_TOP"], set(self.samples),
                            scene_id=self.scene_id, where=self.where_sd)
        lidar_stamps = np.asarray([int(sd["timestamp"]) for sd in lidar_chain], dtype=np.int64)
        for i, stamp in enumerate(self.stamps):
            sd = lidar_chain[int(np.argmin(np.abs(lidar_stamps - stamp)))]
            path = self.root / sd["filename"]
            if not path.is_file():
                raise SceneError(f"LiDAR file of sample_data {sd['token']} is missing",
                                 scene_id=self.scene_id, path=path,
                                 fix="download the LiDAR sweeps or ingest with lidar off")
            raw = np.fromfile(path, dtype=np.float32)
            if raw.size % 5:
                raise SceneError(f"LiDAR file holds {raw.size} floats, not rows of 5 "
                                 f"(x, y, z, intensity, ring)", scene_id=self.scene_id, path=path,
                                 fix="re-download the file or ingest with lidar off")
            pts = raw.reshape(-1, 5)[:, :3].astype(np.float64)
            _, lidar2ego = self.calib_of(sd)
            save_points(self.out_dir, i,
                        transform_points(self.world @ self.ego_of(sd) @ lidar2ego, pts))
