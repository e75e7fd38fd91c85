"""Inference sets: the true novel views of synthetic scenes, and scoring generated videos.

An inference build (``manifest.kind: inference``) has one row per (scene, camera, clip, offset):
the recording as source, the final checkpoint's shifted render as condition and, for a synthetic
scene, the street's exact view from the shifted poses as target. Those targets are rendered here
by the ray caster into the build (``media/<scene_id>/truth/<camera>/<clip>/truth<+2m>.mkv``,
lossless FFV1), so scores against them measure the model, not a codec.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from paradrive.manifest import MediaFile, media_uri, offset_token

TRUTH_DIR = "truth"
TRUTH_CODEC = "ffv1"   # lossless: the target is the ray caster's pixels exactly

Truth = Callable[[dict, float, np.ndarray], "MediaFile | None"]


def truth_file(camera: str, clip: str, offset_m: float) -> str:
    """Scene-relative name of a true novel view: ``truth/<camera>/<clip>/truth<+2m>.mkv``."""
    from paradrive.video import container_suffix

    return f"{TRUTH_DIR}/{camera}/{clip}/truth{offset_token(offset_m)}{container_suffix(TRUTH_CODEC)}"


def no_truth(clip: dict, offset_m: float, novel_c2w: np.ndarray) -> None:
    """A real log: the novel view is unknown."""
    return None


def truth_renderer(scene_dir: str | Path, build_dir: str | Path, clips: dict) -> Truth:
    """``truth(clip, offset_m, novel_c2w)`` for the scene of ``clips`` (its clips.json):
    renders and encodes the street's view from ``novel_c2w`` (F, 4, 4) into ``build_dir`` for a
    synthetic scene; ``no_truth`` for any other."""
    if clips.get("dataset") != "synthetic":
        return no_truth
    from paradrive.eval import scene_ingest_params
    from paradrive.ingest.synthetic import street_from_uri
    from paradrive.uri import parse_uri
    from paradrive.video import encode_video

    street = street_from_uri(parse_uri(str(clips["source"])),
                             scene_ingest_params(Path(scene_dir), None))
    width, height = int(clips["width"]), int(clips["height"])
    sid = str(clips["scene_id"])

    def truth(clip: dict, offset_m: float, novel_c2w: np.ndarray) -> MediaFile:
        fx, fy, cx, cy = clips["cameras"][clip["camera"]]["intrinsics"]
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        rgb = street.render(novel_c2w, K, width, height)["rgb"]
        uri = media_uri(sid, truth_file(clip["camera"], clip["clip"], offset_m))
        path = Path(build_dir) / uri
        path.parent.mkdir(parents=True, exist_ok=True)
        info = encode_video(path, rgb, float(clips["fps"]), codec=TRUTH_CODEC)
        return MediaFile(src=path, uri=uri, sha256=info["sha256"], bytes=info["bytes"])

    return truth


__all__ = ["TRUTH_CODEC", "no_truth", "truth_file", "truth_renderer"]
