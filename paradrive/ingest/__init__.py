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


def select_cameras(available, wanted, *, scene_id: str, where) -> list[str]:
    """The cameras to ingest: ``wanted`` (or all when None), each of which must be available."""
    if wanted is None:
        return list(available)
    missing = [c for c in wanted if c not in available]
    if missing:
        raise SceneError(f"calibration missing for camera(s) {', '.join(missing)} "
                         f"(log has: {', '.join(available) or 'none'})", scene_id=scene_id,
                         path=where, fix="choose cameras the log has with ingest.cameras")
    return list(wanted)
