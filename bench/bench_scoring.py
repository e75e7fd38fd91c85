"""Seconds a video of the scores that need no weights (``paradrive eval --build --videos``):
camera accuracy (RErr / TErr: the source video's model, then each generated video located in it)
and TCE, at the paper's clip size (121 frames of 832x480, ``--frames``, ``--size``).

The videos are the synthetic street's (seed 7, front camera): the recording and its exact views
``--offsets`` metres to the side, encoded as H.264 the way a model's outputs arrive, so the
errors measured beside the seconds are those of a perfect model (and, for the recording scored
against each offset, of a model that ignores the requested camera). The baseline, in the same
process: decoding the video once, as every metric must.

    .venv/bin/python bench/bench_scoring.py --workdir /tmp/bench-scoring
    .venv/bin/python bench/bench_scoring.py --frames 25 --size 320x192 --offsets 1,2
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def videos(workdir: Path, frames: int, width: int, height: int, offsets: list[float]) -> dict:
    """The recording and the shifted true views as .mp4 under ``workdir`` (made once), with
    their cameras and intrinsics."""
    from paradrive import geometry
    from paradrive.synthetic.street import SyntheticStreet
    from paradrive.video import encode_video

    street = SyntheticStreet(seed=7, frames=frames, width=width, height=height, cameras=("front",))
    cam = street.cameras["front"]
    K = np.asarray(cam.K(), dtype=np.float64)
    recorded = street.c2w("front")
    ego = street.ego2world()
    trajectories = {0.0: recorded, **{d: geometry.lateral_shift(recorded, ego, d) for d in offsets}}
    paths = {}
    workdir.mkdir(parents=True, exist_ok=True)
    for d, c2w in trajectories.items():
        path = workdir / f"street-{width}x{height}-{frames}{d:+g}m.mp4"
        if not path.is_file():
            rgb = street.render(c2w, K, width, height, frames=list(range(frames)))["rgb"]
            encode_video(path, rgb, 10.0)
        paths[d] = path
    return {"paths": paths, "c2w": trajectories, "K": K}


def timed(fn):
    start, cpu = time.perf_counter(), time.process_time()
    out = fn()
    return out, round(time.perf_counter() - start, 3), round(time.process_time() - cpu, 3)


def measure(made: dict, offsets: list[float]) -> dict:
    from paradrive.scoring import camera as C
    from paradrive.scoring.flow import tce
    from paradrive.video import decode_frames

    settings = C.CameraSettings()
    source, decode_s, _ = timed(lambda: decode_frames(made["paths"][0.0]))
    n = len(source)
    frames = C.sampled_frames(n, settings.stride)
    model, model_s, model_cpu = timed(lambda: C.triangulate_source(
        source[frames], made["c2w"][0.0][frames], made["K"], settings))
    out: dict = {"frames": n, "size": f"{source.shape[2]}x{source.shape[1]}",
                 "sampled": len(frames), "decode_seconds": decode_s,
                 "source_model": {"seconds": model_s, "cpu_seconds": model_cpu,
                                  "points": model.points}, "videos": []}
    for d in offsets:
        video = decode_frames(made["paths"][d])
        for name, frames_of in (("true view", video), ("recording", source)):
            found, locate_s, locate_cpu = timed(lambda v=frames_of: C.locate(
                model, v[frames], made["K"], settings))
            errors = C.camera_errors(found, made["c2w"][d][frames])
            entry = {"offset_m": d, "video": name, "locate_seconds": locate_s,
                     "locate_cpu_seconds": locate_cpu, **errors.__dict__}
            if name == "true view":
                pairs, tce_s, tce_cpu = timed(lambda v=video: tce(v))
                entry.update(tce=round(float(pairs.mean()), 3), tce_seconds=tce_s,
                             tce_cpu_seconds=tce_cpu)
            out["videos"].append(entry)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/bench-scoring"))
    parser.add_argument("--frames", type=int, default=121)
    parser.add_argument("--size", default="832x480", help="width x height")
    parser.add_argument("--offsets", default="1,4", help="comma-separated lateral offsets, m")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    offsets = [float(v) for v in args.offsets.split(",")]
    import os

    import torch

    made, render_s, _ = timed(lambda: videos(args.workdir, args.frames, width, height, offsets))
    result = {"machine": {"cpus": os.cpu_count(), "load": os.getloadavg()[0],
                          "cpu_capability": torch.backends.cpu.get_cpu_capability()},
              "render_seconds": render_s, **measure(made, offsets)}
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
