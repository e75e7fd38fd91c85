"""``synthetic:<name>?seed=…&frames=…`` scenes: render the procedural street into a canonical scene."""

from __future__ import annotations

from typing import TYPE_CHECKING

from pathlib import Path

import numpy as np

from paradrive.actors import first_frames
from paradrive.errors import SceneError
from paradrive.ingest import select_cameras
from paradrive.scene import Frame, FrameCamera, Scene, write_image
from paradrive.uri import SceneURI

if TYPE_CHECKING:
    from paradrive.contracts.params import IngestParams

# URI query keys and their types; the stage's synthetic_* params are the defaults.
QUERY_KEYS = {"seed": int, "frames": int, "width": int, "height": int, "curvature": float,
              "speed": float, "cameras": str, "traffic": int}


def street_from_uri(uri: SceneURI, params: IngestParams):
    """The SyntheticStreet a URI names, with the ingest parameters as defaults."""
    from paradrive.synthetic import SyntheticStreet
    from paradrive.synthetic.street import CAMERA_NAMES

    query = {}
    for key, value in uri.query.items():
        if key not in QUERY_KEYS:
            raise SceneError(f"unknown synthetic option {key!r} in {uri.text!r}",
                             scene_id=uri.scene_id, fix=f"use one of {', '.join(QUERY_KEYS)}")
        try:
            query[key] = QUERY_KEYS[key](value)
        except ValueError as exc:
            raise SceneError(f"synthetic option {key}={value!r} is not a {QUERY_KEYS[key].__name__}",
                             scene_id=uri.scene_id, fix="fix the scene URI") from exc
    kwargs = dict(
        name=uri.path, seed=query.get("seed", 7),
        frames=query.get("frames", params.synthetic_frames),
        width=query.get("width", params.synthetic_width),
        height=query.get("height", params.synthetic_height),
        curvature=query.get("curvature", params.synthetic_curvature),
        lidar=params.lidar,
    )
    if "speed" in query:
        kwargs["speed_mps"] = query["speed"]
    if "traffic" in query:  # traffic=0: parked cars only
        kwargs["traffic"] = bool(query["traffic"])
    if "cameras" in query:  # the URI's rig wins, like its other keys
        kwargs["cameras"] = query["cameras"]
    else:
        kwargs["cameras"] = tuple(select_cameras(CAMERA_NAMES, params, "synthetic",
                                                 scene_id=uri.scene_id, where=uri.text))
    return SyntheticStreet(**kwargs)


def read(uri: SceneURI, out_dir: Path, params: IngestParams, scene_id: str) -> Scene:
    street = street_from_uri(uri, params)
    cam_names = list(street.cameras)
    ext, quality = params.image_ext, params.jpeg_quality
    n = street.frames if params.max_frames is None else min(street.frames, params.max_frames)
    ego = street.ego2world()[:n]
    stamps = street.timestamps_us()[:n]
    cameras = {}
    frames = [Frame(index=i, timestamp_us=int(stamps[i]), ego2world=ego[i], cameras={})
              for i in range(n)]
    for name in cam_names:
        spec = cameras[name] = street.cameras[name]
        c2w = street.c2w(name)[:n]
        batch = 8
        for start in range(0, n, batch):
            views = street.render(c2w[start:start + batch], spec.K(), spec.width, spec.height,
                                  frames=np.arange(start, min(start + batch, n)))
            for j in range(len(views["rgb"])):
                i = start + j
                rel = f"images/{name}/{i:06d}.{ext}"
                write_image(out_dir / rel, views["rgb"][j], quality=quality)
                if params.sky_masks:
                    mask = (views["sky"][j].astype(np.uint8) * 255)
                    write_image(out_dir / "masks" / "sky" / name / f"{i:06d}.png", mask)
                frames[i].cameras[name] = FrameCamera(image=rel, c2w=c2w[i])
    if params.lidar:
        for i in range(n):
            pts = street.lidar_points(i).astype(np.float32)
            path = out_dir / "lidar" / f"{i:06d}.npy"
            path.parent.mkdir(parents=True, exist_ok=True)
            np.save(path, pts)
    return Scene(scene_id=scene_id, dataset="synthetic", source=uri.text, fps=float(street.fps),
                 cameras=cameras, frames=frames, actors=first_frames(street.actors(), n),
                 extra={"synthetic": {"name": street.name, "seed": street.seed,
                                      "frames": street.frames, "curvature": street.curvature}})
