"""CLIP-V's network: a CLIP image encoder (Radford et al. 2021) loaded with ``transformers``'
CLIPModel from a local folder, giving each frame's L2-normalised image embedding; CLIP-V of a video
pair is then the mean cosine similarity of matching frames (:func:`paradrive.scoring.features.clip_v`).

Frames are prepared as CLIP's own image processor does, in torch on the network's device: the
shorter side resized to the folder's ``size.shortest_edge`` (bicubic, antialiased: PIL's filter),
rounded to 8-bit as PIL returns it, the centre ``crop_size`` square cut out, scaled to [0, 1] and
normalised by ``image_mean`` / ``image_std`` (from ``preprocessor_config.json``; without one, the
model's ``image_size`` and OpenAI's CLIP mean and std).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from paradrive.scoring.networks import Weights, as_frames, weights_sha256

__all__ = ["ClipFeatures", "ClipPreprocess", "OPENAI_MEAN", "OPENAI_STD", "BATCH"]

OPENAI_MEAN = (0.48145466, 0.4578275, 0.40821073)
OPENAI_STD = (0.26862954, 0.26130258, 0.27577711)
BATCH = 32   # frames per forward pass


@dataclass(frozen=True)
class ClipPreprocess:
    """How a CLIP folder wants its images: shorter side, centre crop (height, width), mean, std."""
    shortest_edge: int
    crop: tuple[int, int]
    mean: tuple[float, float, float]
    std: tuple[float, float, float]

    @classmethod
    def of_folder(cls, folder: Path) -> ClipPreprocess:
        vision = json.loads((folder / "config.json").read_text()).get("vision_config", {})
        image_size = int(vision.get("image_size", 224))
        pre = folder / "preprocessor_config.json"
        cfg = json.loads(pre.read_text()) if pre.is_file() else {}
        size = cfg.get("size", image_size)
        crop = cfg.get("crop_size", image_size)
        edge = int(size.get("shortest_edge", image_size) if isinstance(size, dict) else size)
        hw = (int(crop["height"]), int(crop["width"])) if isinstance(crop, dict) else (int(crop), int(crop))
        return cls(edge, hw, tuple(cfg.get("image_mean", OPENAI_MEAN)), tuple(cfg.get("image_std", OPENAI_STD)))

    def __call__(self, frames: torch.Tensor) -> torch.Tensor:
        """frames: (B, 3, H, W) in [0, 1] -> (B, 3, crop_h, crop_w) normalised pixel values."""
        h, w = frames.shape[-2:]
        short, long = (h, w) if h <= w else (w, h)
        new_long = int(self.shortest_edge * long / short)
        size = (self.shortest_edge, new_long) if h <= w else (new_long, self.shortest_edge)
        x = F.interpolate(frames * 255.0, size=size, mode="bicubic", align_corners=False, antialias=True)
        x = x.round().clamp(0, 255) / 255.0
        ch, cw = self.crop
        top, left = (size[0] - ch) // 2, (size[1] - cw) // 2
        x = x[..., max(top, 0):max(top, 0) + ch, max(left, 0):max(left, 0) + cw]
        mean = torch.tensor(self.mean, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
        std = torch.tensor(self.std, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
        return (x - mean) / std


class ClipFeatures:
    """CLIP-V's extractor: (T, H, W, 3) uint8 frames -> (T, D) float64 L2-normalised image
    embeddings (D: the model's projection size), every frame."""

    metric = "clip_v"

    def __init__(self, weights: Weights, device: torch.device):
        from transformers import CLIPModel
        from transformers.utils import logging as hf_logging

        hf_logging.disable_progress_bar()      # one line per video is the command's to print
        self.device = device
        self.model = CLIPModel.from_pretrained(str(weights.path), local_files_only=True).float().eval().to(device)
        self.preprocess = ClipPreprocess.of_folder(weights.path)
        self.weights_sha256 = weights_sha256(weights)

    @torch.inference_mode()
    def features(self, frames: np.ndarray) -> np.ndarray:
        out = []
        for i in range(0, len(frames), BATCH):
            pixels = self.preprocess(as_frames(frames[i:i + BATCH], self.device))
            pooled = self.model.vision_model(pixel_values=pixels).pooler_output
            emb = self.model.visual_projection(pooled)
            out.append(F.normalize(emb.double(), dim=-1).cpu().numpy())
        return np.concatenate(out, axis=0) if out else np.zeros((0, self.model.config.projection_dim))
