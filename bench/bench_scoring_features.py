"""Seconds a frame and a video of the feature metrics' networks (``paradrive eval --metrics
fid,fvd,clip_v,iq``) at the paper's clip size (832x480, ``--size``): FID's Inception-v3, FVD's
I3D (one 16-frame clip a video), CLIP-V's CLIP image encoder (ViT-B/32 or ViT-L/14 shapes,
``--clip``) and IQ's MUSIQ, each loaded through ``load_extractor`` from a weights file of its
real architecture with random values (the seconds do not depend on the values), ``--frames``
frames a call. A video's seconds are a frame's times 121 (``--video-frames``); for FVD, one clip.
The baseline, in the same process: turning the frames into float tensors (``as_frames``).

    .venv/bin/python bench/bench_scoring_features.py --frames 2 --device cpu
    .venv/bin/python bench/bench_scoring_features.py --device cuda --frames 32 --clip l14
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

CLIP_SHAPES = {   # (vision width, layers, heads, patch, projection): OpenAI's released shapes
    "b32": (768, 12, 12, 32, 512),
    "l14": (1024, 24, 16, 14, 768),
}


def write_weights(folder: Path, metric: str, clip: str) -> Path:
    """A weights file (or CLIP folder) of ``metric``'s architecture with torch's initial values."""
    if metric == "clip_v":
        from transformers import CLIPConfig, CLIPModel

        width, layers, heads, patch, proj = CLIP_SHAPES[clip]
        config = CLIPConfig(text_config=dict(num_hidden_layers=1, hidden_size=64, intermediate_size=64,
                                             num_attention_heads=2),
                            vision_config=dict(hidden_size=width, num_hidden_layers=layers, num_attention_heads=heads,
                                               intermediate_size=4 * width, patch_size=patch, image_size=224),
                            projection_dim=proj)
        path = folder / f"clip-{clip}"
        CLIPModel(config).save_pretrained(path)
        return path
    from paradrive.scoring.i3d import InceptionI3d
    from paradrive.scoring.inception import FIDInceptionV3
    from paradrive.scoring.musiq import MUSIQ

    net = {"fid": FIDInceptionV3, "fvd": InceptionI3d, "iq": MUSIQ}[metric]()
    path = folder / f"{metric}.pth"
    torch.save(net.state_dict(), path)
    return path


def timed(fn, repeat: int) -> tuple[float, float]:
    """(wall, CPU) seconds of the fastest of ``repeat`` calls."""
    best = (float("inf"), float("inf"))
    for _ in range(repeat):
        start, cpu = time.perf_counter(), time.process_time()
        fn()
        best = min(best, (time.perf_counter() - start, time.process_time() - cpu))
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="832x480", help="width x height")
    parser.add_argument("--frames", type=int, default=2, help="frames a call (FVD: always one 16-frame clip)")
    parser.add_argument("--video-frames", type=int, default=121)
    parser.add_argument("--metrics", default="fid,fvd,clip_v,iq")
    parser.add_argument("--clip", choices=sorted(CLIP_SHAPES), default="b32")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--repeat", type=int, default=2)
    args = parser.parse_args()

    from paradrive.scoring.features import as_frames, check_weights, load_extractor
    from paradrive.scoring.i3d import CLIP_FRAMES

    width, height = (int(v) for v in args.size.split("x"))
    rng = np.random.default_rng(0)
    result: dict = {"size": args.size, "frames_a_call": args.frames, "torch_threads": torch.get_num_threads(),
                    "cpu_capability": torch.backends.cpu.get_cpu_capability(),
                    "load_average_before": os.getloadavg()[0], "metrics": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for metric in args.metrics.split(","):
            n = CLIP_FRAMES if metric == "fvd" else args.frames
            frames = rng.integers(0, 256, (n, height, width, 3), dtype=np.uint8)
            extractor = load_extractor(check_weights(metric, write_weights(Path(tmp), metric, args.clip)),
                                       device=args.device)
            extractor.features(frames[:1] if metric != "fvd" else frames)     # warm-up
            wall, cpu = timed(lambda: extractor.features(frames), args.repeat)
            per_frame = wall / n
            result["metrics"][metric] = {
                "frames": n, "seconds": round(wall, 3), "cpu_seconds": round(cpu, 3),
                "seconds_a_frame": round(per_frame, 4),
                "seconds_a_video": round(wall if metric == "fvd" else per_frame * args.video_frames, 2),
                **({"clip": args.clip} if metric == "clip_v" else {})}
        device = torch.device("cuda" if args.device in ("auto", "cuda") and torch.cuda.is_available() else "cpu")
        frames = rng.integers(0, 256, (args.frames, height, width, 3), dtype=np.uint8)
        result["baseline_as_frames_seconds"] = round(timed(lambda: as_frames(frames, device), args.repeat)[0], 4)
    result["device"] = str(device)
    result["load_average_after"] = os.getloadavg()[0]
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
