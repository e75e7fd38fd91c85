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
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from paradrive.actors import dynamic_mask, moving_actors
from paradrive.io import TEMPORARY_MARK, no_room_named, temporary_name
from paradrive.scene import Scene, load_scene, write_image, write_scene
from paradrive.contracts.base import StageContext
from paradrive.contracts.params import IngestParams as Params
# read back by later stages and eval from contracts; named here too, as the ingest stage's own
from paradrive.contracts.params import params_of, recorded_params, recorded_values  # noqa: F401
from paradrive.contracts.layout import DataLayout, SceneLayout
from paradrive.errors import ConfigError
from paradrive.uri import SceneURI, parse_uri

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


def check_uri(scene_uri: str, ingest: Mapping[str, Any] | None = None) -> None:
    """Refuse, before any work, a URI whose own values no ingest could take (a ConfigError, a
    usage error): its reader's ``check(uri)`` where it has one (``video:``'s keys and ranges;
    ``synthetic:``'s, and with ``ingest``, the build's ingest parameters, the defaults they give
    the street), and a scene id too long for the files named after it (:func:`check_name_length`)."""
    uri = parse_uri(scene_uri)
    check = getattr(importlib.import_module(READERS[uri.kind]), "check", None)
    if check is not None and uri.kind == "synthetic":
        check(uri, ingest)
    elif check is not None:
        check(uri)
    check_name_length(uri)


# The longest name of a file or folder that ext4, XFS, Btrfs and ZFS hold, in bytes.
NAME_MAX = 255


def scene_file_names(scene_id: str) -> list[str]:
    """Every name the data root gives a file or folder of scene ``scene_id``: its folder (and
    its media folder in a build), ``logs/<id>.log``, ``locks/<id>.lock``, ``<id>.json`` (a URL
    root's lease and its sync record), and the temporary name of each while it is written
    (:func:`paradrive.io.temporary_name`)."""
    layout = DataLayout(Path("."))
    finals = [scene_id, layout.log(scene_id).name, layout.lock(scene_id).name, f"{scene_id}.json"]
    return finals + [temporary_name(Path(name)).name for name in finals]


def check_name_length(uri: SceneURI) -> None:
    """Refuse a URI whose scene id makes a file name longer than :data:`NAME_MAX` bytes (the
    build would fail at its first lock or temporary with "File name too long")."""
    scene_id = uri.scene_id
    longest = max(scene_file_names(scene_id), key=lambda name: len(name.encode()))
    size = len(longest.encode())
    if size <= NAME_MAX:
        return
    most = len(scene_id) - (size - NAME_MAX)
    shown = longest.replace(scene_id, "<id>")
    if TEMPORARY_MARK in shown:   # the random part of a temporary name
        shown = shown[:shown.index(TEMPORARY_MARK) + len(TEMPORARY_MARK)] + "<random>"
    how = ("give the street a shorter name (synthetic:<name>?...)" if uri.kind == "synthetic"
           else "rename the file, or give the scene a shorter name with '#<name>' at the end of "
                "the URI")
    raise ConfigError(f"scene URI {uri.text!r}: its scene id {scene_id} is {len(scene_id)} "
                      f"characters, and a file named after it ({shown}) would be {size} bytes, "
                      f"over the {NAME_MAX}-byte limit on a file name; shorten the id to at most "
                      f"{most} characters: {how}")


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
        # a reader's own writes on a full disk (numpy's short write) are named as the scene's
        with no_room_named(scene_dir, tmp):
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
