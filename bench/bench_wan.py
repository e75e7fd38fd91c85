"""Wan2.1 at the paper's size on one device: the VAE encode of one clip and training steps of
ReCamDriving on the 1.3B transformer, random weights (nothing is downloaded).

    .venv/bin/python bench/bench_wan.py [--device cuda] [--steps 3] [--stages 1,2]
    .venv/bin/python bench/bench_wan.py --tiny --device cpu --threads 1    # the same code, tiny sizes

Full size: Wan2.1's VAE configuration (diffusers' AutoencoderKLWan defaults: base_dim 96,
dim_mult [1, 2, 4, 4], 2 residual blocks, temporal downsampling [False, True, True]) encodes one
121 x 480 x 832 clip in bf16; then, for each stage asked, ``--steps`` training steps (after one
warm-up step) of :class:`paradrive.wan.recam.ReCamDrivingWan` on the Wan2.1-T2V-1.3B
configuration (:func:`paradrive.wan.recam.wan21_t2v_1_3b_config`): 31 target + 31 source latent
frames of 60 x 104 (96,720 tokens), the empty prompt's 512 x 4096 embedding, gradient
checkpointing, bf16 autocast over fp32 weights, AdamW on the stage's trained parameters, the
trainer's flow-matching loss. Each part prints one JSON line with its rate and peak memory
(CUDA: ``torch.cuda.max_memory_allocated``; CPU: the process's peak resident size).
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

FULL = {"frames": 121, "height": 480, "width": 832, "text_tokens": 512}
TINY = {"frames": 5, "height": 48, "width": 80, "text_tokens": 8}


def _sync(device) -> None:
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _reset_peak(device) -> None:
    import torch

    if device.type == "cuda":
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)


def _peak_mb(device) -> float:
    import torch

    if device.type == "cuda":
        return round(torch.cuda.max_memory_allocated(device) / 2**20, 1)
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)   # KiB on Linux


def vae_encode(device, sizes: dict, tiny: bool) -> dict:
    """One clip through the VAE encoder (normalised posterior mean)."""
    import torch
    from diffusers import AutoencoderKLWan

    from paradrive.wan.vae import encode_video, make_tiny_vae

    dtype = torch.bfloat16 if device.type == "cuda" else torch.float32
    with torch.device(device):
        vae = make_tiny_vae(0) if tiny else AutoencoderKLWan()   # diffusers' defaults: Wan2.1's VAE
    vae = (vae.to(device=device) if dtype == torch.float32 else vae.to(device=device, dtype=dtype)).eval()
    video = torch.rand(1, 3, sizes["frames"], sizes["height"], sizes["width"], device=device) * 2 - 1
    _reset_peak(device)
    _sync(device)
    t0 = time.perf_counter()
    latents = encode_video(vae, video)
    _sync(device)
    seconds = time.perf_counter() - t0
    return {"part": "vae_encode", "clip": [sizes["frames"], sizes["height"], sizes["width"]],
            "latents": list(latents.shape[1:]), "dtype": str(dtype).removeprefix("torch."),
            "seconds": round(seconds, 3), "clips_per_second": round(1 / seconds, 4), "peak_memory_mb": _peak_mb(device)}


def train_steps(device, sizes: dict, stage: int, steps: int, tiny: bool) -> dict:
    """``steps`` timed training steps of ``stage`` (after one warm-up step)."""
    import torch
    from diffusers import WanTransformer3DModel

    from paradrive.train.flow import flow_matching_loss
    from paradrive.wan.recam import (ReCamDrivingWan, make_tiny_transformer, trainable_parameters,
                                     wan21_t2v_1_3b_config)
    from paradrive.train.wan import latent_frame_indices

    with torch.device(device):
        transformer = make_tiny_transformer(0) if tiny else WanTransformer3DModel(**wan21_t2v_1_3b_config())
        frames = len(latent_frame_indices(sizes["frames"]))
        model = ReCamDrivingWan(transformer, rendering=stage == 2, max_frames=frames).to(device)
    model.enable_gradient_checkpointing(True)
    params = trainable_parameters(model, stage)
    optimizer = torch.optim.AdamW(params, lr=1e-4)
    shape = (1, 16, frames, sizes["height"] // 8, sizes["width"] // 8)
    g = torch.Generator(device="cpu").manual_seed(0)
    z = {k: torch.randn(shape, generator=g).to(device) for k in ("target", "source", "condition")}
    camera = torch.randn(1, frames, 12, generator=g).to(device)
    text = torch.randn(1, sizes["text_tokens"], int(transformer.config.text_dim), generator=g).to(device)
    autocast = torch.autocast(device.type, dtype=torch.bfloat16, enabled=device.type == "cuda")

    def step(k: int) -> float:
        optimizer.zero_grad(set_to_none=True)
        cond = z["condition"] if stage == 2 else None
        with autocast:
            loss = flow_matching_loss(lambda x, t: model(x, t, z["source"], camera, text, cond).float(), z["target"],
                                      torch.Generator().manual_seed(k))
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        optimizer.step()
        return float(loss.detach())

    step(0)                                   # warm-up: kernels chosen, optimiser state allocated
    _reset_peak(device)
    _sync(device)
    t0 = time.perf_counter()
    losses = [step(k + 1) for k in range(steps)]
    _sync(device)
    seconds = time.perf_counter() - t0
    tokens = 2 * frames * (shape[3] // 2) * (shape[4] // 2)
    return {"part": f"train_stage{stage}", "latents": list(shape[1:]), "tokens": tokens, "gradient_checkpointing": True,
            "trained_parameters": sum(p.numel() for p in params), "steps": steps,
            "iterations_per_second": round(steps / seconds, 4), "seconds_per_step": round(seconds / steps, 3),
            "loss": round(losses[-1], 4), "peak_memory_mb": _peak_mb(device)}


def main() -> None:
    import torch

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--tiny", action="store_true", help="tiny models and clips (5 x 48 x 80): the CPU form")
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--stages", default="1,2")
    ap.add_argument("--parts", default="vae,train", help="vae, train or both")
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        print(json.dumps({"bench": "wan", "skipped": "torch sees no CUDA GPU on this machine"}))
        return
    sizes = TINY if args.tiny else FULL
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    torch.manual_seed(0)
    if "vae" in args.parts:
        print(json.dumps({"bench": "wan", "device": name, **vae_encode(device, sizes, args.tiny)}), flush=True)
    if "train" in args.parts:
        for stage in (int(s) for s in args.stages.split(",")):
            print(json.dumps({"bench": "wan", "device": name, **train_steps(device, sizes, stage, args.steps,
                                                                            args.tiny)}), flush=True)


if __name__ == "__main__":
    main()
