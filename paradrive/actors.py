"""Tracked objects of a scene (``scene.json`` ``actors``): records, checks, interpolation, masks.

An actor is a box with a size (length, width, height in metres) and a per-frame pose
``box2world`` in the scene world. Box frame: origin at the box centre, x along the heading
(length), y left (width), z up. Frames are the scene's ``Frame.index`` values.

Log readers build actors with ``Actor`` and ``interpolate_track``, then keep the good ones with
``keep_valid``: a broken actor (bad size, non-finite pose, a frame the scene does not have,
two boxes in one frame, unknown class) is dropped with a log line naming the scene, the file and
the field, and the scene ingests without it. This module imports no pipeline stage.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Iterable

import numpy as np

from paradrive import geometry
from paradrive.errors import SceneError
from paradrive.contracts.layout import SceneLayout

log = logging.getLogger(__name__)

CLASSES = ("vehicle", "pedestrian", "cyclist", "other")
# Waymo label.proto Label.Type -> class; TYPE_SIGN and TYPE_UNKNOWN are static or unlabelled
# and dropped, as DriveStudio keeps only Vehicle, Pedestrian and Cyclist
WAYMO_TYPES = {1: "vehicle", 2: "pedestrian", 4: "cyclist"}
WAYMO_DROPPED_TYPES = (0, 3)
# nuScenes categories by DriveStudio's lists (datasets/nuscenes/nuscenes_preprocess.py): rigid
# vehicles; people, animals, bicycles and motorcycles non-rigid; everything else is not an actor
NUSCENES_RIGID = ("vehicle.bus.bendy", "vehicle.bus.rigid", "vehicle.car", "vehicle.construction",
                  "vehicle.emergency.ambulance", "vehicle.emergency.police", "vehicle.trailer",
                  "vehicle.truck")
NUSCENES_NONRIGID = {"animal": "other", "human.pedestrian.adult": "pedestrian",
                     "human.pedestrian.child": "pedestrian",
                     "human.pedestrian.construction_worker": "pedestrian",
                     "human.pedestrian.personal_mobility": "pedestrian",
                     "human.pedestrian.police_officer": "pedestrian",
                     "human.pedestrian.stroller": "pedestrian",
                     "human.pedestrian.wheelchair": "pedestrian",
                     "vehicle.bicycle": "cyclist", "vehicle.motorcycle": "cyclist"}
NUSCENES_STATIC = ("movable_object.barrier", "movable_object.debris",
                   "movable_object.pushable_pullable", "movable_object.trafficcone",
                   "static_object.bicycle_rack")


@dataclass
class Actor:
    """One tracked object.

    frames: (T,) int scene frame indices, increasing; box2world: (T, 4, 4) float64 box-to-world;
    size: (3,) length, width, height (m).
    """

    id: str
    cls: str
    rigid: bool
    size: np.ndarray
    frames: np.ndarray
    box2world: np.ndarray

    def to_json(self) -> dict:
        return {"id": self.id, "class": self.cls, "rigid": bool(self.rigid),
                "size": [float(v) for v in self.size],
                "track": [{"frame": int(f), "box2world": [float(v) for v in p.reshape(16)]}
                          for f, p in zip(self.frames, self.box2world)]}

    def centres(self) -> np.ndarray:
        """(T, 3) box centres in the world."""
        return self.box2world[:, :3, 3]

    def pose_at(self, frame: int) -> np.ndarray | None:
        """box2world (4, 4) at scene frame ``frame``, or None when the track has none there."""
        hit = np.flatnonzero(self.frames == frame)
        return self.box2world[hit[0]] if len(hit) else None


def actor_from_json(doc: dict) -> Actor:
    """An Actor from its scene.json entry (KeyError / TypeError / ValueError when malformed)."""
    track = list(doc["track"])
    return Actor(id=str(doc["id"]), cls=str(doc["class"]), rigid=bool(doc["rigid"]),
                 size=np.asarray(doc["size"], dtype=np.float64).reshape(3),
                 frames=np.asarray([int(t["frame"]) for t in track], dtype=np.int64),
                 box2world=np.asarray([t["box2world"] for t in track],
                                      dtype=np.float64).reshape(-1, 4, 4))


def actor_from_boxes(actor_id: str, cls: str, rigid: bool, frames, poses, sizes) -> Actor:
    """An Actor from per-frame boxes: frames (T,), poses (T, 4, 4), sizes (T, 3) as logged.

    Logs give each frame's box its own size; the track's size is their median, or the first
    bad one (NaN or not positive), so that ``keep_valid`` names it.
    """
    sizes = np.asarray(sizes, dtype=np.float64).reshape(-1, 3)
    bad = ~(np.isfinite(sizes) & (sizes > 0)).all(axis=1)
    size = sizes[bad][0] if bad.any() else np.median(sizes, axis=0)
    return Actor(id=actor_id, cls=cls, rigid=rigid, size=size,
                 frames=np.asarray(frames, dtype=np.int64),
                 box2world=np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4))


def log_dropped(actor_id: str, problem: str, *, scene_id: str, where: object) -> None:
    """The log line of an actor left out of a scene that still ingests."""
    log.warning("%s", SceneError(f"actor {actor_id}: {problem}; dropped", scene_id=scene_id,
                                 path=where, fix="fix the annotation in the log"))


def class_of_nuscenes(category: str) -> tuple[str, bool] | None:
    """(class, rigid) of a nuScenes category name, None for static ones; KeyError when unknown."""
    if category in NUSCENES_RIGID:
        return "vehicle", True
    if category in NUSCENES_NONRIGID:
        return NUSCENES_NONRIGID[category], False
    if category in NUSCENES_STATIC:
        return None
    raise KeyError(category)


def class_of_name(name: str) -> tuple[str, bool] | None:
    """(class, rigid) of a DriveStudio ``class_name`` (Waymo's ``Vehicle`` ..., or a nuScenes
    category); None for static ones; KeyError when unknown."""
    simple = {"vehicle": ("vehicle", True), "pedestrian": ("pedestrian", False),
              "cyclist": ("cyclist", False), "sign": None, "unknown": None}
    if name.lower() in simple:
        return simple[name.lower()]
    return class_of_nuscenes(name)


# --------------------------------------------------------------------------- poses

def box_pose(centre, heading: float) -> np.ndarray:
    """box2frame (4, 4) of an upright box: centre (3,), heading (rad about +z)."""
    return geometry.make_pose(geometry.rotation_about("z", float(heading)), centre)


def slerp(q0: np.ndarray, q1: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Spherical interpolation of unit quaternions (4,), (4,) at weights w (N,) -> (N, 4)."""
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly equal: the linear blend is exact to rounding
        out = q0[None] + w[:, None] * (q1 - q0)[None]
        return out / np.linalg.norm(out, axis=1, keepdims=True)
    theta = math.acos(dot)
    a = np.sin((1.0 - w) * theta) / math.sin(theta)
    b = np.sin(w * theta) / math.sin(theta)
    return a[:, None] * q0[None] + b[:, None] * q1[None]


def interpolate_track(key_times: np.ndarray, key_poses: np.ndarray,
                      times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Poses at ``times`` from keyed poses: linear position, slerp rotation, no extrapolation.

    key_times: (K,) increasing; key_poses: (K, 4, 4); times: (N,).
    Returns (inside (N,) bool: time within [first, last] key, poses (M, 4, 4) for those).
    """
    key_times = np.asarray(key_times, dtype=np.float64)
    times = np.asarray(times, dtype=np.float64)
    inside = (times >= key_times[0]) & (times <= key_times[-1])
    t = times[inside]
    right = np.clip(np.searchsorted(key_times, t, side="right"), 1, len(key_times) - 1)
    out = np.tile(np.eye(4), (len(t), 1, 1))
    for k in np.unique(right):
        sel = right == k
        t0, t1 = key_times[k - 1], key_times[k]
        w = np.clip((t[sel] - t0) / (t1 - t0), 0.0, 1.0) if t1 > t0 else np.zeros(sel.sum())
        p0, p1 = key_poses[k - 1], key_poses[k]
        out[sel, :3, 3] = p0[:3, 3] + w[:, None] * (p1[:3, 3] - p0[:3, 3])
        quats = slerp(geometry.rotation_to_quaternion(p0[:3, :3]),
                      geometry.rotation_to_quaternion(p1[:3, :3]), w)
        out[sel, :3, :3] = geometry.quaternion_to_rotation(quats)
    if len(key_times) == 1:
        out[:] = key_poses[0]
    return inside, out


# --------------------------------------------------------------------------- checks

def actor_problem(actor: Actor, frames: set[int]) -> str | None:
    """What is wrong with an actor (naming the field), or None when it is sound."""
    if actor.cls not in CLASSES:
        return f"class {actor.cls!r} is not one of {', '.join(CLASSES)}"
    size = np.asarray(actor.size, dtype=np.float64)
    if size.shape != (3,) or not np.isfinite(size).all() or (size <= 0).any():
        return f"size {size.tolist()} is not three positive lengths (length, width, height)"
    if len(actor.frames) == 0:
        return "track is empty"
    missing = sorted(set(int(f) for f in actor.frames) - frames)
    if missing:
        return f"track frame {missing[0]} is not a frame of the scene"
    values, counts = np.unique(actor.frames, return_counts=True)
    if (counts > 1).any():
        return f"two boxes with this id in frame {int(values[counts > 1][0])} (duplicate id)"
    bad = np.flatnonzero(~geometry.is_rigid(actor.box2world, tol=1e-4))
    if len(bad):
        what = "is not finite" if not np.isfinite(actor.box2world[bad[0]]).all() else "is not rigid"
        return f"box2world (heading/centre) at frame {int(actor.frames[bad[0]])} {what}"
    return None


def keep_valid(actors: Iterable[Actor], frames: Iterable[int], *, scene_id: str,
               where: object) -> list[Actor]:
    """The sound actors, tracks sorted by frame; each broken one is dropped with a log line."""
    known = {int(f) for f in frames}
    good = []
    for actor in actors:
        problem = actor_problem(actor, known)
        if problem is not None:
            log_dropped(actor.id, problem, scene_id=scene_id, where=where)
            continue
        order = np.argsort(actor.frames, kind="stable")
        actor.frames, actor.box2world = actor.frames[order], actor.box2world[order]
        good.append(actor)
    return good


def first_frames(actors: Iterable[Actor], n: int) -> list[Actor]:
    """The actors' tracks cut to frames 0 .. n-1; actors left with no frame are left out."""
    cut = [Actor(a.id, a.cls, a.rigid, a.size, a.frames[a.frames < n], a.box2world[a.frames < n])
           for a in actors]
    return [a for a in cut if len(a.frames)]


def is_moving(actor: Actor, threshold_m: float) -> bool:
    """True when the box centre gets farther than ``threshold_m`` from where it starts."""
    c = actor.centres()
    return bool(len(c) and np.linalg.norm(c - c[0], axis=1).max() > threshold_m)


def moving_actors(actors: Iterable[Actor], threshold_m: float | None) -> list[Actor]:
    """The actors that move farther than ``threshold_m`` (the ingest's ``moving_threshold_m``);
    none when it is None (the scene was ingested without dynamic masks)."""
    return [] if threshold_m is None else [a for a in actors if is_moving(a, threshold_m)]


def read_tracks(scene_dir: Path) -> list[tuple[str, np.ndarray]]:
    """(class, box centres (T, 3)) of each actor of ``scene_dir/scene.json``; [] without one."""
    import json

    path = SceneLayout(Path(scene_dir)).scene_json
    if not path.is_file():
        return []
    found = [actor_from_json(a) for a in json.loads(path.read_text()).get("actors", [])]
    return [(a.cls, a.centres()) for a in found]


# --------------------------------------------------------------------------- masks

def _pixel_window(half: np.ndarray, box2cam: np.ndarray, K: np.ndarray, width: int,
                  height: int) -> tuple[slice, slice] | None:
    """Rows and columns that can see the box (its corners' image rectangle, a pixel wider), the
    whole image when the box reaches behind the camera, None when it is wholly behind."""
    signs = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)]) * 2.0 - 1.0
    corners = (signs * half) @ box2cam[:3, :3].T + box2cam[:3, 3]
    z = corners[:, 2]
    if (z <= 1e-6).all():
        return None
    if (z <= 1e-6).any():
        return slice(0, height), slice(0, width)
    u = K[0, 0] * corners[:, 0] / z + K[0, 2]
    v = K[1, 1] * corners[:, 1] / z + K[1, 2]
    u0, u1 = (int(np.clip(np.floor(x), 0, width)) for x in (u.min() - 1, u.max() + 2))
    v0, v1 = (int(np.clip(np.floor(x), 0, height)) for x in (v.min() - 1, v.max() + 2))
    return (slice(v0, v1), slice(u0, u1)) if u1 > u0 and v1 > v0 else None


def box_footprint(box2world: np.ndarray, size, c2w: np.ndarray, K: np.ndarray, width: int,
                  height: int) -> np.ndarray:
    """bool (H, W): pixels whose ray (through the pixel centre) meets the box.

    box2world, c2w: (4, 4) (c2w OpenCV); size: (3,) length, width, height; K: (3, 3).
    """
    half = 0.5 * np.asarray(size, dtype=np.float64)
    mask = np.zeros((height, width), dtype=bool)
    window = _pixel_window(half, geometry.invert(c2w) @ box2world, K, width, height)
    if window is None:
        return mask
    rows, cols = window
    cam2box = geometry.invert(box2world) @ c2w
    o = cam2box[:3, 3]
    u = (np.arange(cols.start, cols.stop) + 0.5 - K[0, 2]) / K[0, 0]
    v = (np.arange(rows.start, rows.stop) + 0.5 - K[1, 2]) / K[1, 1]
    rays = np.stack(np.broadcast_arrays(u[None, :], v[:, None], np.ones((1, 1))), -1)
    d = rays @ cam2box[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / np.where(d == 0.0, 1e-30, d)
        ta = (-half - o) * inv
        tb = (half - o) * inv
    t_near = np.minimum(ta, tb).max(-1)
    t_far = np.maximum(ta, tb).min(-1)
    mask[rows, cols] = (t_far >= np.maximum(t_near, 0.0)) & (t_far > 0.0)
    return mask


def dynamic_mask(actors: list[Actor], frame: int, c2w: np.ndarray, K: np.ndarray, width: int,
                 height: int) -> np.ndarray:
    """bool (H, W): the union of the footprints of ``actors`` at scene frame ``frame``."""
    mask = np.zeros((height, width), dtype=bool)
    for actor in actors:
        pose = actor.pose_at(frame)
        if pose is not None:
            mask |= box_footprint(pose, actor.size, c2w, K, width, height)
    return mask


def views_mask(actors: list[Actor], frames, c2w: np.ndarray, K: np.ndarray, width: int,
               height: int) -> np.ndarray:
    """bool (N, H, W): per view (c2w (N, 4, 4) at scene frames (N,)), the actors' footprints."""
    return np.stack([dynamic_mask(actors, int(f), pose, K, width, height)
                     for f, pose in zip(frames, c2w)]).reshape(len(c2w), height, width)
