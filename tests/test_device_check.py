"""bench/device_check.sh, the one-GPU check of the paper-size work: its CPU form runs here with
tiny sizes and prints a rate and a peak memory for every part; its full sizes are checked to go
through Wan2.1's real VAE and 1.3B transformer configurations on the meta device (shapes only)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]


def json_documents(text: str) -> list[dict]:
    decoder, docs, i = json.JSONDecoder(), [], 0
    while i < len(text):
        if text[i].isspace():
            i += 1
            continue
        doc, i = decoder.raw_decode(text, i)
        docs.append(doc)
    return docs


@pytest.mark.slow
def test_the_cpu_form_prints_a_rate_and_a_peak_memory_for_every_part():
    env = {**os.environ, "PY": sys.executable, "PYTHONDONTWRITEBYTECODE": "1"}
    result = subprocess.run(["bash", str(REPO / "bench" / "device_check.sh"), "--cpu"], env=env,
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-2000:]
    docs = json_documents(result.stdout)
    assert not [d for d in docs if "part_failed" in d], docs
    (fit,) = [d for d in docs if d.get("bench") == "gpu"]
    assert all(p["iterations_per_second"] > 0 for p in fit["fit"]["phases"])
    assert fit["render_frames_per_second_832x480"] > 0 and "peak_gpu_mb" in fit["fit"]
    parts = {d["part"]: d for d in docs if d.get("bench") == "wan"}
    assert set(parts) == {"vae_encode", "train_stage1", "train_stage2"}
    assert parts["vae_encode"]["latents"] == [16, 2, 6, 10] and parts["vae_encode"]["clips_per_second"] > 0
    for stage in (1, 2):
        part = parts[f"train_stage{stage}"]
        assert part["iterations_per_second"] > 0 and part["gradient_checkpointing"] and part["peak_memory_mb"] > 0
    assert parts["train_stage2"]["trained_parameters"] > parts["train_stage1"]["trained_parameters"]


def test_the_full_sizes_go_through_wans_real_vae_and_13b_configurations():
    """What the GPU run computes, as shapes: one 121 x 480 x 832 clip through the VAE's encoder and
    a stage-2 training step of the 1.3B model on 2 x 31 latent frames, gradients on exactly the
    trained parameters."""
    from diffusers import AutoencoderKLWan, WanTransformer3DModel

    from paradrive.wan.recam import ReCamDrivingWan, stage_parameter_names, trainable_parameters, wan21_t2v_1_3b_config

    with torch.device("meta"):
        vae = AutoencoderKLWan()
        clip = torch.empty(1, 3, 121, 480, 832)
        model = ReCamDrivingWan(WanTransformer3DModel(**wan21_t2v_1_3b_config()), rendering=True, max_frames=31)
        latents = [torch.empty(1, 16, 31, 60, 104) for _ in range(3)]
        camera, text, t = torch.empty(1, 31, 12), torch.empty(1, 512, 4096), torch.empty(1)
    with torch.no_grad():
        assert vae.encode(clip).latent_dist.mean.shape == (1, 16, 31, 60, 104)
    params = trainable_parameters(model, 2)
    model.enable_gradient_checkpointing(True)
    out = model(latents[0], t, latents[1], camera, text, latents[2])
    assert out.shape == (1, 16, 31, 60, 104)
    out.square().mean().backward()
    assert {n for n, p in model.named_parameters() if p.grad is not None} == stage_parameter_names(model, 2)
    assert sum(p.numel() for p in params) == 566_968_320
