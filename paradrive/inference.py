"""Inference sets: the true novel views of synthetic scenes, and scoring generated videos.

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


def score_videos(build_dir: str | Path, videos_dir: str | Path) -> dict:
    """PSNR / SSIM of each generated video (one per row, named by pair_id) against the row's
    true novel view (resized to the video's size), and their means per offset. Rows without a
    target cannot be scored."""
    from paradrive.video import decode_frames
    from paradrive.errors import ParaDriveError
    from paradrive.metrics import frames_quality
    from paradrive.pairs import build_file, read_index, read_pairs

    build_dir, videos_dir = Path(build_dir), Path(videos_dir)
    index = read_index(build_dir)
    if index.kind != "inference":
        raise ParaDriveError(f"{build_dir}: a {index.kind} build; scoring "
                             f"needs an inference set (paradrive build --kind inference)")
    rows = read_pairs(build_dir, ["pair_id", "offset_m", "target_uri"], index, verify=True).to_pylist()
    scored, missing, no_target = [], [], 0
    for row in rows:
        if row["target_uri"] is None:
            no_target += 1
            continue
        video = generated_video(videos_dir, row["pair_id"])
        if video is None:
            missing.append(row["pair_id"])
            continue
        truth = decode_frames(build_file(build_dir, row["target_uri"], "target", index))
        pred = decode_frames(video)
        if len(pred) != len(truth):
            raise ParaDriveError(f"{video}: {len(pred)} frames, the target has {len(truth)}; "
                                 f"generate the build's frame count")
        truth = resized(truth, pred.shape[2], pred.shape[1])
        scored.append({"pair_id": row["pair_id"], "offset_m": float(row["offset_m"]),
                       **dict(zip(("psnr", "ssim"), frames_quality(pred, truth)))})
    by_offset: dict[float, list[dict]] = {}
    for r in scored:
        by_offset.setdefault(r["offset_m"], []).append(r)
    return {"build": str(build_dir), "videos": str(videos_dir), "rows": scored,
            "missing": missing, "rows_without_target": no_target,
            "by_offset": [{"offset_m": d, "videos": len(rs),
                           "psnr": float(np.mean([r["psnr"] for r in rs])),
                           "ssim": float(np.mean([r["ssim"] for r in rs]))}
                          for d, rs in sorted(by_offset.items())]}


def plot_scores(doc: dict, path: str | Path) -> None:
    """PSNR and SSIM against the lateral offset."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from paradrive.io import atomic_path

    offsets = [r["offset_m"] for r in doc["by_offset"]]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    ax1.plot(offsets, [r["psnr"] for r in doc["by_offset"]], "o-")
    ax2.plot(offsets, [r["ssim"] for r in doc["by_offset"]], "s-")
    for ax, label in ((ax1, "PSNR vs true view (dB)"), (ax2, "SSIM vs true view")):
        ax.set_xlabel("lateral offset (m, left > 0)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    fig.suptitle(f"{Path(doc['videos']).name} against {Path(doc['build']).name}")
    fig.tight_layout()
    with atomic_path(Path(path)) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    plt.close(fig)


__all__ = ["TRUTH_CODEC", "generated_video", "no_truth", "plot_scores", "score_videos",
           "truth_file", "truth_renderer"]
