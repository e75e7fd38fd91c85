"""The ingest stage: a log (any supported kind) becomes one canonical scene.

Each reader ``paradrive.ingest.<kind>.read(uri, out_dir, params, scene_id) -> Scene`` writes the
images under ``out_dir`` and returns the scene (with relative image paths). This module writes
everything into a temporary folder and moves it into ``<data>/scenes/<scene_id>/`` only when the
whole scene is valid, so a failed ingest leaves nothing half-written.
"""

from __future__ import annotations

import importlib
import os
import shutil
from pathlib import Path

from paradrive.actors import write_dynamic_masks
from paradrive.errors import SceneError
from paradrive.io import temporary_name
from paradrive.scene import load_scene, write_scene
from paradrive.uri import parse_uri

READERS = {
    "synthetic": "paradrive.ingest.synthetic",
    "waymo": "paradrive.ingest.waymo",
    "nuscenes": "paradrive.ingest.nuscenes",
    "drivestudio": "paradrive.ingest.drivestudio",
}
# What ingest owns inside a scene folder; later stages' outputs are left alone.
INGEST_ENTRIES = ("scene.json", "images", "masks", "lidar")


def ingest(scene_uri: str, scene_dir: str | Path, params: dict) -> dict:
    """Ingest ``scene_uri`` into ``scene_dir``; returns a small summary."""
    uri = parse_uri(scene_uri)
    scene_dir = Path(scene_dir)
    reader = importlib.import_module(READERS[uri.kind])
    scene_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_name(scene_dir)
    tmp.mkdir(parents=True)
    try:
        scene = reader.read(uri, tmp, params, scene_dir.name)
        scene.scene_id = scene_dir.name
        write_scene(scene, tmp)
        if params.get("moving_threshold_m") is not None:
            write_dynamic_masks(scene, tmp, float(params["moving_threshold_m"]))
        load_scene(tmp)  # validates files too, before anything is published
        scene_dir.mkdir(parents=True, exist_ok=True)
        for name in INGEST_ENTRIES:
            target = scene_dir / name
            if target.is_dir():
                shutil.rmtree(target)
            elif target.exists():
                target.unlink()
            if (tmp / name).exists():
                os.replace(tmp / name, target)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return {"frames": len(scene.frames), "cameras": sorted(scene.cameras),
            "dataset": scene.dataset}


def run_stage(ctx) -> dict:
    return ingest(ctx.scene_uri, ctx.scene_dir, ctx.params)


def requested_cameras(params: dict, dataset: str, *, scene_id: str) -> list[str] | None:
    """The cameras ``ingest.cameras`` asks for in a log of ``dataset`` (None = all the log has).

    ``auto`` is the dataset's fit set, ``ingest.camera_sets[dataset]`` (stages/ingest.yaml).
    """
    wanted = params.get("cameras")
    if wanted is None or isinstance(wanted, (list, tuple)):
        return None if wanted is None else list(wanted)
    if wanted != "auto":
        raise SceneError(f"ingest.cameras = {wanted!r} is neither auto, null nor a list of cameras",
                         scene_id=scene_id, fix="set ingest.cameras to auto or e.g. [front]")
    sets = params.get("camera_sets") or {}
    if dataset not in sets:
        raise SceneError(f"ingest.cameras is auto but ingest.camera_sets has no {dataset} entry "
                         f"(has: {', '.join(sets) or 'none'})", scene_id=scene_id,
                         fix=f"add camera_sets.{dataset} to stages/ingest.yaml or list the "
                             f"cameras in ingest.cameras")
    return list(sets[dataset])


def select_cameras(available, params: dict, dataset: str, *, scene_id: str, where) -> list[str]:
    """The cameras to ingest (``requested_cameras``), each of which must be in ``available``."""
    wanted = requested_cameras(params, dataset, scene_id=scene_id)
    if wanted is None:
        return list(available)
    missing = [c for c in wanted if c not in available]
    if missing:
        asked = (f"ingest.cameras is auto, the {dataset} fit set (ingest.camera_sets.{dataset})"
                 if params.get("cameras") == "auto" else "ingest.cameras asks for them")
        keep = [c for c in wanted if c in available] or list(available)
        raise SceneError(f"calibration missing for camera(s) {', '.join(missing)} "
                         f"(log has: {', '.join(available) or 'none'}; {asked})",
                         scene_id=scene_id, path=where,
                         fix=f"ingest the cameras the log has, e.g. --set "
                             f"ingest.cameras=[{','.join(keep)}]")
    return list(wanted)
