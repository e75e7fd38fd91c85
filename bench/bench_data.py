"""Throughput of the trainer's adapter (paradrive.data) on pairs of 3 x 121 frames at 480x832.

Makes its own build: synthetic moving frames encoded with PyAV (H.264 yuv420p, as the clip stage
writes them) behind a real clips.json and a real manifest, so it runs anywhere. Prints JSON:

* baseline: samples/s reading every frame of the three files of a pair (plain PyAV decode to
  RGB arrays, nothing else): the floor any loader pays;
* adapter with 0, 2 and 4 DataLoader workers: samples/s of PairDataset (decode, crop/resize,
  float tensors in [-1, 1], poses), and its ratio to the baseline;
* PairDataset[i] called in-process (no DataLoader collate copy), float32 and bfloat16;
* a 25-frame window late in the clip, with the x264 default GOP and with a 30-frame GOP (seeking
  decodes from the keyframe before the window, so a shorter GOP decodes fewer frames);
* the share of a trainer step spent waiting for data, for an assumed step time
  (``--step-seconds``; the adapter cannot measure the trainer), and the workers needed to keep up.

Usage: python bench/bench_data.py [--pairs 4] [--frames 121] [--height 480] [--width 832]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from paradrive import geometry  # noqa: E402
from paradrive.pipeline import StageRegistry  # noqa: E402
from paradrive.stages.manifest import build_manifest


def synthetic_frames(seed: int, n: int, h: int, w: int):
    """A textured scene panning sideways: realistic enough for the codec to do real work."""
    rng = np.random.default_rng(seed)
    coarse = rng.integers(0, 255, (h // 16 + 2, (w + 4 * n) // 16 + 2, 3), dtype=np.uint8)
    big = np.repeat(np.repeat(coarse, 16, axis=0), 16, axis=1).astype(np.float32)
    y, x = np.mgrid[0:h, 0:w]
    shade = (0.6 + 0.4 * np.sin(x / 37.0 + seed) * np.cos(y / 23.0))[..., None]
    for i in range(n):
        yield np.clip(big[:h, 4 * i:4 * i + w] * shade, 0, 255).astype(np.uint8)


def encode(path: Path, frames, fps: int = 10, gop: int | None = None) -> dict:
    import av

    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), "w") as out:
        stream = None
        for img in frames:
            if stream is None:
                stream = out.add_stream("libx264", rate=fps)
                stream.height, stream.width = img.shape[:2]
                stream.pix_fmt = "yuv420p"
                stream.options = {"crf": "18", "preset": "veryfast",
                                  **({"g": str(gop), "keyint_min": str(gop)} if gop else {})}
            for p in stream.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
                out.mux(p)
        for p in stream.encode():
            out.mux(p)
    data = path.read_bytes()
    return {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}


def make_build(root: Path, pairs: int, n: int, h: int, w: int, gop: int | None) -> Path:
    """One scene, one clip: a target, one condition and ``pairs`` shifted sources."""
    scene = root / "data" / "scenes" / "bench"
    ego = np.stack([geometry.translation(x=float(i)) for i in range(n)])
    cam2ego = geometry.make_pose(geometry.OPENCV_TO_FLU, [1.5, 0, 1.6])
    c2w = ego @ cam2ego
    streams = {}
    streams["target"] = {"file": "clips/front/middle/target.mp4", "kind": "target",
                         **encode(scene / "clips/front/middle/target.mp4",
                                  synthetic_frames(0, n, h, w), gop=gop)}
    streams["cond@000100"] = {"file": "clips/front/middle/cond@000100.mp4", "kind": "condition",
                              "iteration": 100,
                              **encode(scene / "clips/front/middle/cond@000100.mp4",
                                       synthetic_frames(1, n, h, w), gop=gop)}
    for k in range(pairs):
        d = float(k + 1) * (1 if k % 2 == 0 else -1)
        name = f"source{d:+g}m"
        shifted = geometry.lateral_shift(c2w, ego, d)
        streams[name] = {"file": f"clips/front/middle/{name}.mp4", "kind": "source",
                         "iteration": 30000, "offset_m": d,
                         "c2w": [m.reshape(16).tolist() for m in shifted],
                         **encode(scene / f"clips/front/middle/{name}.mp4",
                                  synthetic_frames(2 + k, n, h, w), gop=gop)}
    doc = {"schema_version": 1, "scene_id": "bench", "dataset": "synthetic", "source": "bench",
           "fps": 10.0, "width": w, "height": h,
           "cameras": {"front": {"intrinsics": [w * 0.8, w * 0.8, w / 2, h / 2]}},
           "fit": {"iteration": 30000, "train_psnr": 30.0, "train_ssim": 0.9},
           "clips": [{"camera": "front", "clip": "middle", "frame_start": 0, "num_frames": n,
                      "frame_indices": list(range(n)), "timestamps_us": [i * 100_000 for i in range(n)],
                      "c2w": [m.reshape(16).tolist() for m in c2w], "streams": streams,
                      "quality": {"cond@000100": {"psnr": 20.0, "ssim": 0.6}}}]}
    (scene / "clips" / "clips.json").write_text(json.dumps(doc))
    build = root / "manifests" / "bench"
    params = StageRegistry().resolve(None, {"manifest": {"quality": False}}).typed("manifest")
    build_manifest(build, [{"scene_id": "bench", "scene_dir": str(scene)}], params)
    return build


def baseline(build: Path, repeats: int) -> float:
    """samples/s decoding every frame of the three files of each pair (PyAV, RGB arrays)."""
    import av

    from paradrive.data import PairDataset

    ds = PairDataset(build)
    t0 = time.perf_counter()
    count = 0
    for _ in range(repeats):
        for i in range(len(ds)):
            row = ds.row(i)
            for role in ("source", "condition", "target"):
                with av.open(str(build / row[f"{role}_uri"])) as c:
                    frames = [f.to_ndarray(format="rgb24") for f in c.decode(c.streams.video[0])]
                    np.stack(frames)
            count += 1
    return count / (time.perf_counter() - t0)


def adapter(build: Path, workers: int, repeats: int, **options) -> float:
    import torch
    from torch.utils.data import DataLoader

    from paradrive.data import PairDataset

    ds = PairDataset(build, **options)
    order = list(range(len(ds))) * repeats
    loader = DataLoader(ds, batch_size=1, num_workers=workers, sampler=order,
                        persistent_workers=False, prefetch_factor=2 if workers else None)
    t0 = time.perf_counter()
    count = 0
    for batch in loader:
        assert batch["source"].dtype == torch.float32
        count += 1
    return count / (time.perf_counter() - t0)


def in_process(build: Path, repeats: int, **options) -> float:
    """samples/s of PairDataset[i] called directly (no DataLoader, no collate copy)."""
    from paradrive.data import PairDataset

    ds = PairDataset(build, **options)
    t0 = time.perf_counter()
    for _ in range(repeats):
        for i in range(len(ds)):
            ds[i]
    return repeats * len(ds) / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--pairs", type=int, default=4)
    ap.add_argument("--frames", type=int, default=121)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--width", type=int, default=832)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--workers", default="0,2,4")
    ap.add_argument("--step-seconds", type=float, default=3.0,
                    help="assumed trainer step time for one sample (a video diffusion model on "
                         "one GPU at 121x480x832; the adapter cannot measure it)")
    args = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    out: dict = {"pairs": args.pairs, "frames": args.frames,
                 "size": [args.height, args.width], "cpus": os.cpu_count(),
                 "machine": platform.machine(), "python": platform.python_version()}
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        build = make_build(Path(tmp) / "default_gop", args.pairs, args.frames, args.height,
                           args.width, gop=None)
        short = make_build(Path(tmp) / "gop30", args.pairs, args.frames, args.height,
                           args.width, gop=30)
        out["setup_seconds"] = round(time.perf_counter() - t0, 1)
        base = baseline(build, args.repeats)
        out["baseline_samples_per_s"] = round(base, 3)
        full = {}
        for k in [int(x) for x in args.workers.split(",")]:
            sps = adapter(build, k, args.repeats)
            full[str(k)] = {"samples_per_s": round(sps, 3), "ratio_to_baseline": round(sps / base, 3)}
        out["adapter_121_frames"] = full
        out["in_process_getitem_samples_per_s"] = {
            "float32": round(in_process(build, args.repeats), 3),
            "bfloat16": round(in_process(build, args.repeats, dtype=torch.bfloat16), 3)}
        window = {"num_frames": 25, "frame_offset": args.frames - 25}
        out["window_25_frames_at_end"] = {
            "x264_default_gop": round(adapter(build, 0, args.repeats, **window), 3),
            "gop_30": round(adapter(short, 0, args.repeats, **window), 3),
            "unit": "samples/s, 0 workers"}
        t_sample = 1.0 / full["0"]["samples_per_s"]
        step = args.step_seconds
        best = max(v["samples_per_s"] for v in full.values())
        out["trainer_step_estimate"] = {
            "assumed_step_seconds": step,
            "data_seconds_per_sample_one_process": round(t_sample, 3),
            "share_of_step_without_workers": round(t_sample / (t_sample + step), 3),
            "workers_to_hide_loading": math.ceil(t_sample / step),
            "stall_share_with_best_loader": round(max(0.0, 1 / best - step) / max(1 / best, step), 3),
        }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
