"""Random-weight networks of the feature metrics' real architectures, written where the real
weights would lie: a weights file in each published layout (FID's Inception-v3, FVD's I3D, IQ's
MUSIQ) and a tiny CLIPModel folder, for the tests of the networks and of ``paradrive eval``.

Weights are drawn so activations keep their scale through the depth (He-normal convolutions,
batch norms with spread statistics), so features of different frames differ."""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from paradrive.scoring.i3d import InceptionI3d
from paradrive.scoring.inception import FIDInceptionV3
from paradrive.scoring.musiq import MUSIQ

FILE_NAMES = {"fid": "pt_inception-2015-12-05-random.pth", "fvd": "rgb_imagenet-random.pt",
              "iq": "musiq_spaq_ckpt-random.pth", "clip_v": "clip-tiny-random"}

CLIP_IMAGE = 32   # the tiny CLIP's input size (its image processor resizes and crops to it)


def randomised(net: nn.Module, seed: int) -> nn.Module:
    """``net`` with every parameter and norm statistic drawn from a seeded generator."""
    g = torch.Generator(device="cpu").manual_seed(seed)
    for m in net.modules():
        if isinstance(m, (nn.Conv2d, nn.Conv3d)):
            nn.init.kaiming_normal_(m.weight, nonlinearity="relu", generator=g)
            if m.bias is not None:
                nn.init.normal_(m.bias, std=0.02, generator=g)
        elif isinstance(m, (nn.BatchNorm2d, nn.BatchNorm3d)):
            with torch.no_grad():
                m.running_mean.copy_(torch.randn(m.num_features, generator=g, device="cpu") * 0.1)
                m.running_var.copy_(torch.rand(m.num_features, generator=g, device="cpu") + 0.5)
                m.weight.copy_(torch.rand(m.num_features, generator=g, device="cpu") + 0.5)
                nn.init.normal_(m.bias, std=0.1, generator=g)
        elif isinstance(m, nn.Linear):
            nn.init.normal_(m.weight, std=m.in_features ** -0.5, generator=g)
            nn.init.normal_(m.bias, std=0.02, generator=g)
    for name, p in net.named_parameters():
        if name.endswith(("position_emb", "scale_emb", ".cls")) or name == "transformer_encoder.cls":
            with torch.no_grad():
                p.copy_(torch.randn(p.shape, generator=g, device="cpu") * 0.02)
    return net


def write_state_dict(net: nn.Module, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(net.state_dict(), path)
    return path


def write_fid_weights(folder: Path, seed: int = 0) -> Path:
    return write_state_dict(randomised(FIDInceptionV3(), seed), folder / FILE_NAMES["fid"])


def write_fvd_weights(folder: Path, seed: int = 0) -> Path:
    return write_state_dict(randomised(InceptionI3d(), seed), folder / FILE_NAMES["fvd"])


def write_iq_weights(folder: Path, seed: int = 0) -> Path:
    return write_state_dict(randomised(MUSIQ(), seed), folder / FILE_NAMES["iq"])


def write_clip_folder(folder: Path, seed: int = 0) -> Path:
    """A tiny random CLIPModel (ViT, 2 layers, 32 x 32 input) with its image processor's config."""
    from transformers import CLIPConfig, CLIPImageProcessor, CLIPModel

    torch.manual_seed(seed)
    config = CLIPConfig(
        text_config=dict(vocab_size=99, bos_token_id=0, eos_token_id=2, pad_token_id=1, hidden_size=32,
                         intermediate_size=37, num_hidden_layers=2, num_attention_heads=4,
                         max_position_embeddings=16),
        vision_config=dict(image_size=CLIP_IMAGE, patch_size=8, hidden_size=32, intermediate_size=37,
                           num_hidden_layers=2, num_attention_heads=4),
        projection_dim=24)
    path = folder / FILE_NAMES["clip_v"]
    CLIPModel(config).eval().save_pretrained(path)
    CLIPImageProcessor(size={"shortest_edge": CLIP_IMAGE},
                       crop_size={"height": CLIP_IMAGE, "width": CLIP_IMAGE}).save_pretrained(path)
    return path


WRITERS = {"fid": write_fid_weights, "fvd": write_fvd_weights, "clip_v": write_clip_folder,
           "iq": write_iq_weights}


def write_all(folder: Path, metrics: tuple[str, ...] = ("fid", "fvd", "clip_v", "iq")) -> dict[str, Path]:
    """Random weights of each metric in ``metrics`` under ``folder``: {metric: file or folder}."""
    return {m: WRITERS[m](Path(folder)) for m in metrics}
