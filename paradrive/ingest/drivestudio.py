"""``drivestudio:<folder>``: one scene as DriveStudio's preprocessors leave it (``processed/training/023``).

Waymo flavour (``ego_pose/`` present)::

    images/<t:03d>_<cam>.jpg       raw (distorted) camera images, cam = CameraName - 1
    ego_pose/<t:03d>.txt           4x4 vehicle -> global
    extrinsics/<cam>.txt           4x4 camera (x forward, y left, z up) -> vehicle
    intrinsics/<cam>.txt           f_u f_v c_u c_v k1 k2 p1 p2 k3
    sky_masks/<t:03d>_<cam>.png    255 = sky (optional)
    lidar/<t:03d>.bin              float32 rows: origin(3), point(3) in the vehicle frame, ...

    c2w = inv(ego_0) · ego_t · extrinsic · OPENCV_TO_FLU, images undistorted here.

nuScenes flavour (``extrinsics/<t:03d>_<cam>.txt``)::

    extrinsics/<t:03d>_<cam>.txt   4x4 camera (OpenCV) -> global, per frame
    intrinsics/<cam>.txt           fx fy cx cy 0 0 0 0 0
    lidar/<t:03d>.bin + lidar_pose/<t:03d>.txt   float32 (N, 4) in the LiDAR frame; LiDAR -> global

It stores no ego pose: the ego frame is taken as the front camera's pose with vehicle axes
(x forward, y left, z up), so the world is the first front-camera pose, levelled to those axes.
Both may hold ``instances/instances_info.json`` (per instance: id, class_name, and per annotated
frame ``frame_idx``, ``obj_to_world`` (4x4, global) and ``box_size`` (length, width, height)) and
``instances/frame_instances.json`` (frame -> instances): they become the scene's actors.
Neither flavour stores timestamps: frames are ``1e6 / fps`` us apart, fps from ``?fps=``, else
10 (Waymo) or the ``processed_<N>Hz`` folder name (nuScenes, 2 Hz keyframes by default).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import json
import re
from pathlib import Path

import numpy as np

from paradrive import actors as act
from paradrive import geometry
from paradrive.errors import SceneError
from paradrive.ingest import select_cameras
from paradrive.ingest.common import (
    OPENCV_TO_FLU, check_size, checked_pose, decode_jpeg, save_points, store_image,
    transform_points,
)
from paradrive.ingest.undistort import distortion_is_zero, undistort_image
from paradrive.scene import Camera, Frame, FrameCamera, Scene, read_image, write_image
from paradrive.uri import SceneURI

if TYPE_CHECKING:
    from paradrive.contracts.params import IngestParams

WAYMO_CAMERAS = {0: "front", 1: "front_left", 2: "front_right", 3: "side_left", 4: "side_right"}
NUSCENES_CAMERAS = {0: "front", 1: "front_left", 2: "front_right", 3: "back_left",
                    4: "back_right", 5: "back"}


def flavour_of(folder: Path, uri: SceneURI, scene_id: str) -> str:
    if uri.query.get("flavour") in ("waymo", "nuscenes"):
        return uri.query["flavour"]
    if (folder / "ego_pose").is_dir():
        return "waymo"
    if any(re.fullmatch(r"\d+_\d+\.txt", p.name) for p in (folder / "extrinsics").glob("*.txt")):
        return "nuscenes"
    raise SceneError("not a DriveStudio scene folder (no ego_pose/ and no per-frame extrinsics/)",
                     scene_id=scene_id, path=folder,
                     fix="point the URI at one processed scene, e.g. .../processed/training/023")


def load_matrix(path: Path, shape, *, scene_id: str, what: str) -> np.ndarray:
    if not path.is_file():
        raise SceneError(f"{what} file is missing", scene_id=scene_id, path=path,
                         fix="re-run DriveStudio's preprocessing for this scene")
    try:
        values = np.loadtxt(path, dtype=np.float64)
    except ValueError as exc:
        raise SceneError(f"{what} file is not numbers ({exc})", scene_id=scene_id, path=path,
                         fix="re-run DriveStudio's preprocessing for this scene") from exc
    if values.size != int(np.prod(shape)):
        raise SceneError(f"{what} file holds {values.size} numbers, expected {int(np.prod(shape))}",
                         scene_id=scene_id, path=path,
                         fix="re-run DriveStudio's preprocessing for this scene")
    return values.reshape(shape)


def _fps(folder: Path, uri: SceneURI, flavour: str, scene_id: str) -> float:
    if "fps" in uri.query:
        try:
            fps = float(uri.query["fps"])
        except ValueError:
            fps = -1.0
        if not fps > 0:
            raise SceneError(f"fps={uri.query['fps']!r} is not a positive number",
                             scene_id=scene_id, fix="fix the scene URI")
        return fps
    if flavour == "waymo":
        return 10.0
    m = re.search(r"processed_(\d+)Hz", str(folder.resolve()))
    return float(m.group(1)) if m else 2.0


def _frame_numbers(folder: Path, sub: str, pattern: str) -> list[int]:
    found = set()
    for p in (folder / sub).glob("*"):
        m = re.fullmatch(pattern, p.name)
        if m:
            found.add(int(m.group(1)))
    return sorted(found)


# --------------------------------------------------------------------------- instances

def _json_file(path: Path, *, scene_id: str):
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise SceneError(f"{path.name} is not valid JSON ({exc})", scene_id=scene_id, path=path,
                         fix="re-run DriveStudio's preprocessing (objects) for this scene") from exc


def listed_twice(path: Path, *, scene_id: str) -> dict[str, str]:
    """Instances that frame_instances.json lists twice in one frame: {instance: frame}."""
    if not path.is_file():
        return {}
    twice: dict[str, str] = {}
    for frame, listed in dict(_json_file(path, scene_id=scene_id)).items():
        seen: set[str] = set()
        for inst in map(str, listed):
            if inst in seen:
                twice.setdefault(inst, str(frame))
            seen.add(inst)
    return twice


def instance_actor(key: str, doc: dict, position: dict[int, int], known: set[int],
                   world_from_global, *, scene_id: str, where) -> act.Actor | None:
    """One instance's actor (frames as scene positions), or None (static, or dropped and logged)."""
    name = f"drivestudio:{doc.get('id', key) if isinstance(doc, dict) else key}"
    try:
        kind = act.class_of_name(str(doc["class_name"]))
        boxes = doc["frame_annotations"]
        numbers = [int(n) for n in boxes["frame_idx"]]
        poses, sizes = boxes["obj_to_world"], boxes["box_size"]
    except (KeyError, TypeError, ValueError) as exc:
        act.log_dropped(name, f"instance {key} has no valid class_name / frame_annotations "
                              f"({type(exc).__name__}: {exc})", scene_id=scene_id, where=where)
        return None
    if kind is None:
        return None
    missing = [n for n in numbers if n not in known]
    if missing or len(poses) != len(numbers) or len(sizes) != len(numbers):
        problem = (f"frame_idx {missing[0]} is not a frame of the scene" if missing else
                   "frame_idx, obj_to_world and box_size differ in length")
        act.log_dropped(name, problem, scene_id=scene_id, where=where)
        return None
    keep = [j for j, n in enumerate(numbers) if n in position]  # frames past max_frames go
    box2world = [world_from_global @ np.asarray(poses[j], dtype=np.float64) for j in keep]
    return act.actor_from_boxes(name, kind[0], kind[1], [position[numbers[j]] for j in keep],
                                box2world, [sizes[j] for j in keep])


def instance_actors(folder: Path, numbers: list[int], known: set[int], world_from_global, *,
                    scene_id: str) -> list[act.Actor]:
    """The actors of ``instances/`` (none when the folder has no instances_info.json)."""
    where = folder / "instances" / "instances_info.json"
    if not where.is_file():
        return []
    info = _json_file(where, scene_id=scene_id)
    twice = listed_twice(folder / "instances" / "frame_instances.json", scene_id=scene_id)
    position = {n: i for i, n in enumerate(numbers)}
    found = []
    for key, doc in dict(info).items():
        if str(key) in twice:
            act.log_dropped(f"drivestudio:{key}", f"listed twice in frame {twice[str(key)]} of "
                            "frame_instances.json (duplicate id)", scene_id=scene_id, where=where)
            continue
        actor = instance_actor(str(key), doc, position, known, world_from_global,
                               scene_id=scene_id, where=where)
        found += [actor] if actor is not None and len(actor.frames) else []
    return act.keep_valid(found, range(len(numbers)), scene_id=scene_id, where=where)


def read(uri: SceneURI, out_dir: Path, params: IngestParams, scene_id: str) -> Scene:
    folder = Path(uri.path).expanduser()
    _check_folder(folder, scene_id)
    return _Reader(uri, folder, out_dir, params, scene_id).scene()


def _check_folder(folder: Path, scene_id: str) -> None:
    if not folder.is_dir():
        raise SceneError("DriveStudio scene folder does not exist", scene_id=scene_id, path=folder,
                         fix="check the path in the scene URI")
    outside = [p for p in sorted(folder.rglob("*"))
               if p.is_symlink() and not p.resolve().is_relative_to(folder.resolve())]
    if outside:
        raise SceneError(f"{len(outside)} link(s) in the scene folder lead out of it, e.g. "
                         f"{outside[0].relative_to(folder)} -> {outside[0].resolve()}",
                         scene_id=scene_id, path=folder,
                         fix="copy the files into the folder instead of linking them")


def _check_numbering(numbers: list[int], folder: Path, scene_id: str) -> None:
    if not numbers:
        raise SceneError("scene folder has no frames", scene_id=scene_id, path=folder,
                         fix="re-run DriveStudio's preprocessing for this scene")
    if numbers != list(range(len(numbers))):
        gap = next(i for i, n in enumerate(numbers) if n != i)
        raise SceneError(f"frame {gap:03d} is missing (frames must be numbered 000, 001, ...)",
                         scene_id=scene_id, path=folder,
                         fix="re-run DriveStudio's preprocessing for this scene")


class _Reader:
    """One DriveStudio folder read into a canonical scene, step by step."""

    def __init__(self, uri: SceneURI, folder: Path, out_dir: Path, params: IngestParams, scene_id: str):
        self.uri, self.folder, self.out_dir, self.params = uri, folder, out_dir, params
        self.scene_id = scene_id
        self.flavour = flavour_of(folder, uri, scene_id)
        self.fps = _fps(folder, uri, self.flavour, scene_id)
        ids = WAYMO_CAMERAS if self.flavour == "waymo" else NUSCENES_CAMERAS
        if self.flavour == "waymo":
            available = [name for cid, name in ids.items()
                         if (folder / "extrinsics" / f"{cid}.txt").is_file()]
            numbers = _frame_numbers(folder, "ego_pose", r"(\d+)\.txt")
        else:
            available = [name for cid, name in ids.items()
                         if (folder / "extrinsics" / f"000_{cid}.txt").is_file()]
            numbers = _frame_numbers(folder, "extrinsics", r"(\d+)_0\.txt")
        self.chosen = select_cameras(available, params, self.flavour, scene_id=scene_id,
                                     where=folder / "extrinsics")
        _check_numbering(numbers, folder, scene_id)
        self.known = set(numbers)
        limit = params.max_frames
        self.numbers = numbers[:limit] if limit is not None else numbers
        self.cam_id = {name: cid for cid, name in ids.items()}

    def pose(self, path: Path, what: str) -> np.ndarray:
        return checked_pose(load_matrix(path, (4, 4), scene_id=self.scene_id, what=what),
                            scene_id=self.scene_id, where=path, what=what)

    def global_poses(self) -> tuple[list[np.ndarray], dict[str, np.ndarray], dict[str, list]]:
        """Ego poses, cam2ego and camera poses per frame, in the log's global frame."""
        folder, chosen, cam_id = self.folder, self.chosen, self.cam_id
        if self.flavour == "waymo":
            ego_global = [self.pose(folder / "ego_pose" / f"{t:03d}.txt", f"frame {t} ego pose")
                          for t in self.numbers]
            cam2ego = {cam: self.pose(folder / "extrinsics" / f"{cam_id[cam]}.txt",
                                      f"camera {cam} extrinsic") @ OPENCV_TO_FLU
                       for cam in chosen}
            return ego_global, cam2ego, {cam: [e @ cam2ego[cam] for e in ego_global]
                                         for cam in chosen}
        c2w_global = {cam: [self.pose(folder / "extrinsics" / f"{t:03d}_{cam_id[cam]}.txt",
                                      f"frame {t} camera {cam} pose") for t in self.numbers]
                      for cam in chosen + (["front"] if "front" not in chosen else [])}
        # no ego pose in this flavour: the front camera with vehicle axes stands in for it
        flu = geometry.invert(OPENCV_TO_FLU)
        ego_global = [c @ flu for c in c2w_global["front"]]
        cam2ego = {cam: geometry.invert(ego_global[0]) @ c2w_global[cam][0] for cam in chosen}
        return ego_global, cam2ego, c2w_global

    def scene(self) -> Scene:
        ego_global, cam2ego, c2w_global = self.global_poses()
        world = geometry.invert(ego_global[0])
        frames = [Frame(index=i, timestamp_us=int(round(i * 1e6 / self.fps)),
                        ego2world=world @ ego_global[i], cameras={})
                  for i in range(len(self.numbers))]
        cameras: dict[str, Camera] = {}
        for cam in self.chosen:
            cameras[cam] = self.camera_images(cam, cam2ego[cam], frames,
                                              [world @ c for c in c2w_global[cam]])
        if self.params.lidar and (self.folder / "lidar").is_dir():
            self.lidar([world @ e for e in ego_global], world)
        return Scene(scene_id=self.scene_id, dataset="drivestudio", source=self.uri.text,
                     fps=self.fps, cameras=cameras, frames=frames,
                     actors=instance_actors(self.folder, self.numbers, self.known, world,
                                            scene_id=self.scene_id),
                     extra={"drivestudio": {"flavour": self.flavour, "folder": self.folder.name,
                                            "ego": "vehicle pose" if self.flavour == "waymo" else
                                            "front camera with vehicle axes (no ego pose stored)"}})

    def camera_images(self, cam: str, cam2ego: np.ndarray, frames: list[Frame],
                      c2w: list[np.ndarray]) -> Camera:
        """Store every image of ``cam`` (undistorted) and its sky masks; the camera."""
        sid, folder, cid = self.scene_id, self.folder, self.cam_id[cam]
        intr = load_matrix(folder / "intrinsics" / f"{cid}.txt", (9,), scene_id=sid,
                           what=f"camera {cam} intrinsics")
        fx, fy, cx, cy = (float(v) for v in intr[:4])
        dist = intr[4:9]
        camera = None
        for i, t in enumerate(self.numbers):
            path = folder / "images" / f"{t:03d}_{cid}.jpg"
            if not path.is_file():
                raise SceneError(f"frame {t} camera {cam} image is missing", scene_id=sid,
                                 path=path, fix="re-run DriveStudio's preprocessing, or drop the "
                                                "camera with ingest.cameras")
            data = path.read_bytes()
            pixels = decode_jpeg(data, scene_id=sid, where=path)
            if camera is None:
                camera = Camera(name=cam, width=pixels.shape[1], height=pixels.shape[0],
                                fx=fx, fy=fy, cx=cx, cy=cy, cam2ego=cam2ego)
            check_size(pixels, camera.width, camera.height, scene_id=sid, where=path,
                       what=f"camera {cam} image")
            rel = f"images/{cam}/{i:06d}.{self.params.image_ext}"
            store_image(self.out_dir, rel, pixels, K=camera.K(), dist=dist,
                        quality=self.params.jpeg_quality, original=data)
            frames[i].cameras[cam] = FrameCamera(image=rel, c2w=c2w[i])
            self.sky_mask(folder / "sky_masks" / f"{t:03d}_{cid}.png", cam, i, camera.K(), dist)
        assert camera is not None  # numbers is never empty
        return camera

    def sky_mask(self, path: Path, cam: str, i: int, K: np.ndarray, dist: np.ndarray) -> None:
        if not (self.params.sky_masks and path.is_file()):
            return
        mask = read_image(path, scene_id=self.scene_id)[..., :1]
        if not distortion_is_zero(dist):
            mask = undistort_image(mask, K, dist)
        mask = np.where(mask[..., 0] > 127, 255, 0).astype(np.uint8)
        write_image(self.out_dir / "masks" / "sky" / cam / f"{i:06d}.png", mask)

    def lidar(self, ego2world: list[np.ndarray], world: np.ndarray) -> None:
        """World points of every frame's sweep (``lidar/<frame>.npy``)."""
        sid = self.scene_id
        for i, t in enumerate(self.numbers):
            path = self.folder / "lidar" / f"{t:03d}.bin"
            if not path.is_file():
                continue
            raw = np.fromfile(path, dtype=np.float32)
            if self.flavour == "waymo":
                pts, pose = _waymo_lidar_points(raw, scene_id=sid, path=path), ego2world[i]
            else:
                if raw.size % 4:
                    raise SceneError(f"LiDAR file holds {raw.size} floats, not rows of 4",
                                     scene_id=sid, path=path,
                                     fix="re-run preprocessing or ingest with lidar off")
                pts = raw.reshape(-1, 4)[:, :3]
                pose = world @ self.pose(self.folder / "lidar_pose" / f"{t:03d}.txt",
                                         f"frame {t} LiDAR pose")
            save_points(self.out_dir, i, transform_points(pose, pts.astype(np.float64)))


def _waymo_lidar_points(raw: np.ndarray, *, scene_id: str, path: Path) -> np.ndarray:
    """Points (vehicle frame) of a Waymo-flavour lidar .bin: 14 columns (with flow) or 10."""
    for cols in (14, 10):
        if raw.size % cols:
            continue
        rows = raw.reshape(-1, cols)
        origins, laser = rows[:, 0:3], rows[:, -1]
        plausible = (np.abs(origins).max(initial=0.0) < 10.0
                     and np.all((laser >= 0) & (laser <= 4) & (laser == np.round(laser))))
        if plausible:
            return rows[:, 3:6]
    raise SceneError(f"LiDAR file of {raw.size} floats is neither 14 nor 10 columns per point",
                     scene_id=scene_id, path=path,
                     fix="re-run preprocessing or ingest with lidar off")
