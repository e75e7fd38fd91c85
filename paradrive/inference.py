"""Inference sets: the true novel views of synthetic scenes, and where a model's generated
videos are found (their scoring is :mod:`paradrive.scoring`).

An inference build (``manifest.kind: inference``) has one row per (scene, camera, clip, offset):
the recording as source, the final checkpoint's shifted render as condition and, for a synthetic
scene, the street's exact view from the shifted poses as target. Those targets are rendered here
by the ray caster into the build (``media/<scene_id>/truth/<camera>/<clip>/truth<+2m>.mkv``,
lossless FFV1), so scores against them measure the model, not a codec.
"""

from __future__ import annotations

from pathlib import Path
from collections.abc import Callable

import numpy as np

from paradrive.manifest import MediaFile
from paradrive.pairs import media_uri
from paradrive.contracts.records import ClipRecord, ClipsRecord
from paradrive.streams import format_offset

TRUTH_DIR = "truth"
TRUTH_CODEC = "ffv1"   # lossless: the target is the ray caster's pixels exactly

Truth = Callable[[ClipRecord, float, np.ndarray], "MediaFile | None"]


def truth_file(camera: str, clip: str, offset_m: float) -> str:
    """Scene-relative name of a true novel view: ``truth/<camera>/<clip>/truth<+2m>.mkv``."""
    from paradrive.video import container_suffix

    return f"{TRUTH_DIR}/{camera}/{clip}/truth{format_offset(offset_m)}{container_suffix(TRUTH_CODEC)}"


def no_truth(clip: ClipRecord, offset_m: float, novel_c2w: np.ndarray) -> None:
    """A real log: the novel view is unknown."""
    return None


def scene_ingest_params(scene_dir: Path, fallback: dict | None) -> dict:
    """The parameters the scene was ingested with (its stage marker), else ``fallback``."""
    from paradrive.contracts.layout import SceneLayout
    from paradrive.contracts.params import recorded_values

    recorded = recorded_values(SceneLayout.at(scene_dir))
    return recorded if recorded is not None else dict(fallback or {})


def truth_renderer(scene_dir: str | Path, version_dir: str | Path, clips: ClipsRecord) -> Truth:
    """``truth(clip, offset_m, novel_c2w)`` for the scene of ``clips`` (its clips.json):
    renders and encodes the street's view from ``novel_c2w`` (F, 4, 4) into ``version_dir`` (the
    build version being published) for a synthetic scene; ``no_truth`` for any other."""
    if clips.dataset != "synthetic":
        return no_truth
    from paradrive.ingest.synthetic import street_from_uri
    from paradrive.uri import parse_uri
    from paradrive.video import encode_video

    from paradrive.contracts.params import params_of

    street = street_from_uri(parse_uri(clips.source),
                             params_of(scene_ingest_params(Path(scene_dir), None)))
    width, height, sid = clips.width, clips.height, clips.scene_id

    def truth(clip: ClipRecord, offset_m: float, novel_c2w: np.ndarray) -> MediaFile:
        fx, fy, cx, cy = clips.cameras[clip.camera].intrinsics
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        # the street at each frame's instant: moving actors where they were then
        rgb = street.render(novel_c2w, K, width, height, frames=clip.frame_indices)["rgb"]
        uri = media_uri(sid, truth_file(clip.camera, clip.clip, offset_m))
        path = Path(version_dir) / uri
        path.parent.mkdir(parents=True, exist_ok=True)
        info = encode_video(path, rgb, clips.fps, codec=TRUTH_CODEC)
        return MediaFile(src=path, uri=uri, sha256=info["sha256"], bytes=info["bytes"])

    return truth


# --------------------------------------------------------------------------- scoring

VIDEO_SUFFIXES = (".mp4", ".mkv")


def generated_video(videos_dir: Path, pair_id: str) -> Path | None:
    """``<videos_dir>/<pair_id>.mp4`` (or ``.mkv``); a pair id's ``/`` are folders."""
    from paradrive.io import path_inside

    for suffix in VIDEO_SUFFIXES:
        path = path_inside(videos_dir, f"{pair_id}{suffix}", f"video of {pair_id}")
        if path.is_file():
            return path
    return None


def resized(frames: np.ndarray, width: int, height: int) -> np.ndarray:
    """uint8 (N, H, W, 3) frames at ``width`` x ``height`` (the render stage's area resize): a
    model that generates at a smaller size is scored against the truth at its own size."""
    from paradrive.streams import OutputCamera, crop_resize

    h, w = frames.shape[1:3]
    if (w, h) == (width, height):
        return frames
    out = OutputCamera(width=width, height=height, crop=(0, 0, w, h), K=np.eye(3))
    return np.stack([crop_resize(f, out) for f in frames])


__all__ = ["TRUTH_CODEC", "generated_video", "no_truth", "resized", "truth_file",
           "truth_renderer"]
