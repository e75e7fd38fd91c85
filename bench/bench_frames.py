"""Per-frame work beside the rasterizer: the fit loss's SSIM (forward and gradient) and the
render stage's PNG frame writes, each against its earlier implementation in the same process;
prints JSON.

    .venv/bin/python bench/bench_frames.py [--repeats 50] [--threads 2]

* SSIM: the native kernels against the torch operations (the closed-form gradient through two
  separable filterings), at the demo's training size (160x96) and on a clip's 121 frames at
  320x192 (the clip stage scores each condition so); synthetic street frames.
* PNG: ``scene.write_image`` (zlib level 1, the "up" row filter) against OpenImageIO's defaults
  (level 6, every filter tried per row), a 320x192 street frame; bytes next to the time.
* H.264: ``video.encode_video`` of a 121-frame clip at 320x192 (the clip stage's settings), x264
  held to its AVX2 functions as it is on a CPU with AVX-512, against x264's own choice; where the
  CPU has no AVX-512 both are the same encode. ``--busy`` runs a CPU-bound process on every core.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from spinners import every_core  # noqa: E402  (bench/, the script's own folder)


def _median_seconds(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return sorted(times)[len(times) // 2]


def street_frames():
    """Two neighbouring front-camera frames of the synthetic street at 320x192, uint8."""
    from paradrive.synthetic import SyntheticStreet

    street = SyntheticStreet(seed=7, frames=8, width=320, height=192)
    return street.render(street.c2w("front")[2:4], street.cameras["front"].K(), 320, 192)["rgb"]


def bench_ssim(frames, repeats: int) -> list[dict]:
    import numpy as np
    import torch

    from paradrive import metrics

    f = torch.from_numpy(frames).float() / 255.0
    clip = [torch.from_numpy(np.resize(frames[i], (121, 192, 320, 3))).float() / 255.0
            for i in (0, 1)]
    results = []
    for label, (a, b) in [("fit loss, 160x96", (f[0, ::2, ::2], f[1, ::2, ::2])),
                          ("clip quality, 121 frames of 320x192", clip)]:
        a = a.contiguous().requires_grad_(True)
        native = metrics._native_kernels(a)
        if native is None:
            raise SystemExit("the native kernels did not build here; nothing to compare")

        def run(use_native: bool):
            def step():
                kernels = metrics._native_kernels
                if not use_native:
                    metrics._native_kernels = lambda x: None
                try:
                    s = metrics.ssim(a, b).sum()
                    s.backward()
                finally:
                    metrics._native_kernels = kernels
            return step

        rounds = max(3, repeats // (40 if a.dim() == 4 else 1))
        t_native, t_torch = [], []
        for _ in range(rounds):   # interleaved: a busy spell slows both
            t_native.append(_median_seconds(run(True), 1))
            t_torch.append(_median_seconds(run(False), 1))
        med = lambda v: sorted(v)[len(v) // 2]  # noqa: E731
        results.append({"case": label, "forward_backward_ms": {
            "native": round(med(t_native) * 1000, 3), "torch_ops": round(med(t_torch) * 1000, 3)},
            "speedup": round(med(t_torch) / med(t_native), 2), "rounds": rounds})
    return results


def bench_png(frames, repeats: int) -> dict:
    import OpenImageIO as oiio

    from paradrive.scene import read_image, write_image

    pixels = frames[0]
    with tempfile.TemporaryDirectory() as tmp:
        ours, default = Path(tmp) / "ours.png", Path(tmp) / "default.png"

        def oiio_defaults():
            out = oiio.ImageOutput.create(str(default))
            out.open(str(default), oiio.ImageSpec(320, 192, 3, "uint8"))
            out.write_image(pixels)
            out.close()

        t_ours, t_default = [], []
        for _ in range(repeats):
            t_ours.append(_median_seconds(lambda: write_image(ours, pixels), 1))
            t_default.append(_median_seconds(oiio_defaults, 1))
        assert (read_image(ours) == pixels).all()   # still lossless
        med = lambda v: sorted(v)[len(v) // 2]  # noqa: E731
        return {"case": "PNG write, 320x192 RGB", "ms": {
            "write_image": round(med(t_ours) * 1000, 3),
            "openimageio_defaults": round(med(t_default) * 1000, 3)},
            "bytes": {"write_image": ours.stat().st_size,
                      "openimageio_defaults": default.stat().st_size},
            "speedup": round(med(t_default) / med(t_ours), 2)}


def bench_h264(frames, rounds: int) -> dict:
    import numpy as np

    import paradrive.video as video

    clip = [np.roll(frames[i % 2], 2 * i, axis=1) for i in range(121)]   # a panning clip
    held = video.x264_params()
    times: dict[str, list[float]] = {"held": [], "x264_own": []}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(rounds):   # interleaved: a busy spell slows both
            for name, params in (("held", held), ("x264_own", {})):
                video.x264_params = lambda params=params: params
                t0 = time.perf_counter()
                video.encode_video(Path(tmp) / f"{name}.mp4", clip, 10.0, crf=18, gop=30)
                times[name].append(time.perf_counter() - t0)
    med = lambda v: sorted(v)[len(v) // 2]  # noqa: E731
    return {"case": "H.264 encode, 121 frames at 320x192, crf 18, gop 30", "x264_params": held,
            "s": {k: round(med(v), 3) for k, v in times.items()},
            "ratio_held_over_own": round(med(times["held"]) / med(times["x264_own"]), 3)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--threads", type=int, default=2, help="the native kernels' threads")
    ap.add_argument("--h264-rounds", type=int, default=5)
    ap.add_argument("--busy", action="store_true", help="a CPU-bound process on every core")
    args = ap.parse_args()
    import torch

    from paradrive.devices import set_cpu_kernel_threads

    torch.set_num_threads(1)   # as the stages run torch beside the kernels
    set_cpu_kernel_threads(args.threads)
    frames = street_frames()
    out = {"bench": "frames", "machine": platform.machine(), "threads": args.threads,
           "load_average": [round(x, 2) for x in os.getloadavg()],
           "busy": args.busy}
    with every_core(args.busy):
        out.update(ssim=bench_ssim(frames, args.repeats), png=bench_png(frames, args.repeats),
                   h264=bench_h264(frames, args.h264_rounds))
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
