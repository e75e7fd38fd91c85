"""The ``ingest`` stage (``stages/ingest.yaml``): a log (any supported kind) becomes one
canonical scene.

Each reader ``paradrive.ingest.<kind>.read(uri, out_dir, params, scene_id) -> Scene`` writes the
images under ``out_dir`` and returns the scene (with relative image paths). The stage writes
everything into a temporary folder and moves it into ``<data>/scenes/<scene_id>/`` only when the
whole scene is valid, so a failed ingest leaves nothing half-written.

Credit: ``cameras: auto`` ingests the fit sets of DriveStudio's dataset configs (Waymo ``3cams``,
nuScenes ``6cams``), which the ReCamDriving recipe keeps.
"""

from __future__ import annotations

import importlib
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from paradrive.actors import dynamic_mask, moving_actors
from paradrive.io import temporary_name
from paradrive.scene import Scene, load_scene, write_image, write_scene
from paradrive.contracts.base import StageContext
from paradrive.contracts.params import IngestParams as Params
# read back by later stages and eval from contracts; named here too, as the ingest stage's own
from paradrive.contracts.params import params_of, recorded_params, recorded_values  # noqa: F401
from paradrive.contracts.layout import SceneLayout
from paradrive.uri import parse_uri

READERS = {
    "synthetic": "paradrive.ingest.synthetic",
    "waymo": "paradrive.ingest.waymo",
    "nuscenes": "paradrive.ingest.nuscenes",
    "drivestudio": "paradrive.ingest.drivestudio",
    "video": "paradrive.ingest.video",
}
# What ingest owns inside a scene folder; later stages' outputs are left alone.
INGEST_ENTRIES = ("scene.json", "images", "masks", "lidar")


class IngestSummary(dict[str, Any]):
    """What ingest reports: frames, cameras and dataset of the scene (scene.json is the record)."""

    def summary(self) -> dict[str, Any]:
        return dict(self)


def check_uri(scene_uri: str) -> None:
    """Refuse, before any work, a URI whose own values no ingest could take (a ConfigError, a
    usage error): its reader's ``check(uri)`` where it has one (``video:``'s keys and ranges)."""
    uri = parse_uri(scene_uri)
    check = getattr(importlib.import_module(READERS[uri.kind]), "check", None)
    if check is not None:
        check(uri)


def ingest(scene_uri: str, layout: SceneLayout | Path, params: Params) -> IngestSummary:
    """Ingest ``scene_uri`` into the scene folder ``layout``."""
    layout = SceneLayout.at(layout)
    uri = parse_uri(scene_uri)
    reader = importlib.import_module(READERS[uri.kind])
    scene_dir = layout.root
    scene_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_name(scene_dir)
    tmp.mkdir(parents=True)
    try:
        scene = reader.read(uri, tmp, params, scene_dir.name)
        scene.scene_id = scene_dir.name
        write_scene(scene, tmp)
        if params.moving_threshold_m is not None:
            write_dynamic_masks(scene, tmp, params.moving_threshold_m)
        load_scene(tmp)  # validates files too, before anything is published
        scene_dir.mkdir(parents=True, exist_ok=True)
        for name in INGEST_ENTRIES:
            _replace(tmp / name, scene_dir / name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    summary = IngestSummary(frames=len(scene.frames), cameras=sorted(scene.cameras),
                            dataset=scene.dataset)
    if "video" in scene.extra:  # what SfM found: intrinsics (estimated or given), scale, frames
        summary["video"] = scene.extra["video"]
    return summary


def _replace(src: Path, target: Path) -> None:
    if target.is_dir():
        shutil.rmtree(target)
    elif target.exists():
        target.unlink()
    if src.exists():
        os.replace(src, target)


def write_dynamic_masks(scene: Scene, root: Path, threshold_m: float) -> int:
    """Write ``masks/dynamic/<cam>/<frame:06d>.png`` (255 = a moving actor's box) for every
    image of a scene with actors; returns the number of moving actors."""
    if not scene.actors:
        return 0
    moving = moving_actors(scene.actors, threshold_m)
    for name, cam in scene.cameras.items():
        for frame in scene.frames:
            if name not in frame.cameras:
                continue
            mask = dynamic_mask(moving, frame.index, frame.cameras[name].c2w, cam.K(),
                                cam.width, cam.height)
            write_image(SceneLayout(root).dynamic_mask(name, frame.index),
                        mask.astype(np.uint8) * 255)
    return len(moving)


def run(ctx: StageContext[Params]) -> IngestSummary:
    return ingest(ctx.scene_uri, ctx.layout, ctx.params)
