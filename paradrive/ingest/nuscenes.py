"""``nuscenes:<dataroot>?version=v1.0-mini#scene-0061``: a nuScenes v1.0 scene, read from its JSON tables.

Tables (``<dataroot>/<version>/<table>.json``): scene, sample, sample_data, ego_pose,
calibrated_sensor, sensor (log when present). A camera's frames are its full sample_data chain
(keyframes and sweeps, ~12 Hz), followed by ``next`` from the sample_data of the scene's first
sample while it stays in the scene. The first camera asked for is the frame clock; the other
cameras take their image nearest in time. Each image has its own ego pose, so::

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

import json
from pathlib import Path

import numpy as np

from paradrive import actors as act
from paradrive import geometry
from paradrive.errors import SceneError
from paradrive.ingest import select_cameras
from paradrive.ingest.common import (
    check_increasing, check_size, checked_pose, decode_jpeg, fps_from, max_frames, save_points,
    store_image, transform_points,
)
from paradrive.scene import Camera, Frame, FrameCamera, Scene
from paradrive.uri import SceneURI

REQUIRED_TABLES = ("scene", "sample", "sample_data", "ego_pose", "calibrated_sensor", "sensor")
OPTIONAL_TABLES = ("log", "category", "instance", "sample_annotation")
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


def load_tables(folder: Path, scene_id: str) -> dict[str, dict[str, dict]]:
    """Each table as {token: row}."""
    tables = {}
    for name in REQUIRED_TABLES + OPTIONAL_TABLES:
        path = folder / f"{name}.json"
        if not path.is_file():
            if name in OPTIONAL_TABLES:
                continue
            raise SceneError(f"table {name}.json is missing", scene_id=scene_id, path=path,
                             fix="point the URI at the nuScenes dataroot and version whose "
                                 "tables are complete (re-extract the metadata archive)")
        try:
            rows = json.loads(path.read_text())
            tables[name] = {row["token"]: row for row in rows}
        except (json.JSONDecodeError, KeyError, TypeError) as exc:
            raise SceneError(f"table {name}.json is malformed ({type(exc).__name__}: {exc})",
                             scene_id=scene_id, path=path,
                             fix="re-extract the nuScenes metadata archive") from exc
    return tables


def _get(tables, table: str, token: str, *, scene_id: str, where, referrer: str) -> dict:
    row = tables[table].get(token)
    if row is None:
        raise SceneError(f"{referrer} refers to {table} {token!r}, which is not in {table}.json",
                         scene_id=scene_id, path=where, fix="the tables are inconsistent; "
                                                            "re-extract the metadata archive")
    return row


def _pose(row: dict, *, scene_id: str, where, what: str) -> np.ndarray:
    try:
        q = np.asarray(row["rotation"], dtype=np.float64)
        t = np.asarray(row["translation"], dtype=np.float64)
    except (KeyError, TypeError, ValueError) as exc:
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


def find_scene(tables, uri: SceneURI, scene_id: str, where) -> dict:
    scenes = list(tables["scene"].values())
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
    sd = start
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
    row = tables.get("instance", {}).get(instance)
    if row is None:
        raise KeyError(f"instance {instance!r} is not in instance.json")
    category = tables.get("category", {}).get(row.get("category_token"))
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
    sample_time = {tok: int(tables["sample"][tok]["timestamp"]) for tok in samples}
    by_instance: dict[str, list[dict]] = {}
    for row in tables.get("sample_annotation", {}).values():
        by_instance.setdefault(row.get("instance_token"), []).append(row)
    where = meta / "sample_annotation.json"
    found = [instance_actor(tables, inst, rows, sample_time, stamps, world_from_global,
                            scene_id=scene_id, where=where)
             for inst, rows in by_instance.items()
             if any(r.get("sample_token") in sample_time for r in rows)]
    return act.keep_valid([a for a in found if a is not None], range(len(stamps)),
                          scene_id=scene_id, where=where)


def read(uri: SceneURI, out_dir: Path, params: dict, scene_id: str) -> Scene:
    root = Path(uri.path).expanduser()
    if not root.is_dir():
        raise SceneError("nuScenes dataroot does not exist", scene_id=scene_id, path=root,
                         fix="check the path in the scene URI")
    version = find_version(root, uri, scene_id)
    meta = root / version
    tables = load_tables(meta, scene_id)
    scene_row = find_scene(tables, uri, scene_id, meta / "scene.json")
    # samples of the scene, by walking the sample chain
    samples, token = [], scene_row["first_sample_token"]
    while token:
        sample = _get(tables, "sample", token, scene_id=scene_id, where=meta / "sample.json",
                      referrer=f"scene {scene_row.get('name')}")
        if sample["token"] in samples:
            break
        samples.append(sample["token"])
        token = "" if token == scene_row.get("last_sample_token") else sample.get("next", "")
    scene_samples = set(samples)
    first_sample = samples[0]
    # the first sample's sample_data per channel
    where_sd = meta / "sample_data.json"
    firsts: dict[str, dict] = {}
    for sd in tables["sample_data"].values():
        if sd["sample_token"] == first_sample:
            ch = channel_of(tables, sd, scene_id=scene_id, where=where_sd)
            # a keyframe if there is one, else the earliest
            old = firsts.get(ch)
            if old is None or (sd.get("is_key_frame") and not old.get("is_key_frame")) or (
                    sd.get("is_key_frame") == old.get("is_key_frame") and sd["timestamp"] < old["timestamp"]):
                firsts[ch] = sd
    available = [CHANNEL_TO_CAMERA[ch] for ch in CHANNEL_TO_CAMERA if ch in firsts]
    chosen = select_cameras(available, params, "nuscenes", scene_id=scene_id, where=meta)
    chains = {cam: chain(tables, firsts[CAMERA_TO_CHANNEL[cam]], scene_samples,
                         scene_id=scene_id, where=where_sd) for cam in chosen}
    clock = chains[chosen[0]]
    limit = max_frames(params)
    if limit is not None:
        clock = clock[:limit]
    stamps = [int(sd["timestamp"]) for sd in clock]
    check_increasing(stamps, scene_id=scene_id, where=where_sd,
                     labels=[f"sample_data {sd['token']} (frame {i}, {chosen[0]})"
                             for i, sd in enumerate(clock)])

    ext = params.get("image_ext", "jpg")
    quality = int(params.get("jpeg_quality", 95))
    where_ego = meta / "ego_pose.json"
    where_cs = meta / "calibrated_sensor.json"

    def ego_of(sd):
        row = _get(tables, "ego_pose", sd["ego_pose_token"], scene_id=scene_id, where=where_sd,
                   referrer=f"sample_data {sd['token']}")
        return _pose(row, scene_id=scene_id, where=where_ego, what=f"ego_pose {row['token']}")

    def calib_of(sd):
        row = _get(tables, "calibrated_sensor", sd["calibrated_sensor_token"], scene_id=scene_id,
                   where=where_sd, referrer=f"sample_data {sd['token']}")
        return row, _pose(row, scene_id=scene_id, where=where_cs,
                          what=f"calibrated_sensor {row['token']}")

    world_from_global = geometry.invert(ego_of(clock[0]))
    cameras: dict[str, Camera] = {}
    for cam in chosen:
        sd = chains[cam][0]
        row, cam2ego = calib_of(sd)
        K = np.asarray(row.get("camera_intrinsic") or [], dtype=np.float64)
        if K.shape != (3, 3):
            raise SceneError(f"calibrated_sensor {row['token']} ({cam}) has no 3x3 camera_intrinsic",
                             scene_id=scene_id, path=where_cs, fix="check the calibration tables")
        cameras[cam] = Camera(name=cam, width=int(sd.get("width") or 0),
                              height=int(sd.get("height") or 0), fx=float(K[0, 0]),
                              fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]),
                              cam2ego=cam2ego)
    chain_stamps = {cam: np.asarray([int(sd["timestamp"]) for sd in chains[cam]], dtype=np.int64)
                    for cam in chosen}
    frames = []
    for i, sd_clock in enumerate(clock):
        frame = Frame(index=i, timestamp_us=stamps[i],
                      ego2world=world_from_global @ ego_of(sd_clock), cameras={})
        for cam in chosen:
            sd = sd_clock if cam == chosen[0] else chains[cam][
                int(np.argmin(np.abs(chain_stamps[cam] - stamps[i])))]
            image_path = root / sd["filename"]
            if not image_path.is_file():
                raise SceneError(f"image of sample_data {sd['token']} ({cam}, frame {i}) is missing",
                                 scene_id=scene_id, path=image_path,
                                 fix="download the sweeps/samples archives of this part of the "
                                     "dataset, or drop the camera")
            data = image_path.read_bytes()
            pixels = decode_jpeg(data, scene_id=scene_id, where=image_path)
            c = cameras[cam]
            if c.width == 0:  # older tables leave width/height out
                c.width, c.height = pixels.shape[1], pixels.shape[0]
            check_size(pixels, c.width, c.height, scene_id=scene_id, where=image_path,
                       what=f"camera {cam} image")
            rel = f"images/{cam}/{i:06d}.{ext}"
            store_image(out_dir, rel, pixels, quality=quality,
                        original=data if image_path.suffix.lower() in (".jpg", ".jpeg") else None)
            _, cam2ego = calib_of(sd)
            frame.cameras[cam] = FrameCamera(image=rel,
                                             c2w=world_from_global @ ego_of(sd) @ cam2ego)
        frames.append(frame)
    if params.get("lidar", True) and "LIDAR_TOP" in firsts:
        lidar_chain = chain(tables, firsts["LIDAR_TOP"], scene_samples, scene_id=scene_id,
                            where=where_sd)
        lidar_stamps = np.asarray([int(sd["timestamp"]) for sd in lidar_chain], dtype=np.int64)
        for i, stamp in enumerate(stamps):
            sd = lidar_chain[int(np.argmin(np.abs(lidar_stamps - stamp)))]
            path = root / sd["filename"]
            if not path.is_file():
                raise SceneError(f"LiDAR file of sample_data {sd['token']} is missing",
                                 scene_id=scene_id, path=path,
                                 fix="download the LiDAR sweeps or ingest with lidar off")
            raw = np.fromfile(path, dtype=np.float32)
            if raw.size % 5:
                raise SceneError(f"LiDAR file holds {raw.size} floats, not rows of 5 "
                                 f"(x, y, z, intensity, ring)", scene_id=scene_id, path=path,
                                 fix="re-download the file or ingest with lidar off")
            pts = raw.reshape(-1, 5)[:, :3].astype(np.float64)
            _, lidar2ego = calib_of(sd)
            save_points(out_dir, i, transform_points(world_from_global @ ego_of(sd) @ lidar2ego, pts))
    log = tables.get("log", {}).get(scene_row.get("log_token"), {})
    return Scene(scene_id=scene_id, dataset="nuscenes", source=uri.text,
                 fps=fps_from(stamps, FPS), cameras=cameras, frames=frames,
                 actors=annotation_actors(tables, samples, stamps, world_from_global,
                                          scene_id=scene_id, meta=meta),
                 extra={"nuscenes": {"version": version, "scene": scene_row.get("name"),
                                     "scene_token": scene_row["token"],
                                     "location": log.get("location")}})
