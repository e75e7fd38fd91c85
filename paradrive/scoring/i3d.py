"""FVD's network: the Inflated 3D ConvNet (I3D, Carreira & Zisserman 2017) trained on Kinetics-400,
the network FVD is defined with (Unterthiner et al. 2018), in plain torch with the parameter names
of pytorch-i3d's ``rgb_imagenet.pt`` (the RGB stream, ImageNet-inflated, Kinetics-400 trained) so
that file loads as it is published.

Every convolution and max pool pads as TF's ``SAME`` does (the padding depends on the input
size, the larger half at the end), batch norms have ε = 0.001, and the logits are a biased 1x1x1
convolution after a (2, 7, 7) average pool, averaged over the time steps left.

A video's FVD feature is the 400-d logits (FVD's choice, the TF-hub module's output) of one clip:
its first :data:`CLIP_FRAMES` frames (StyleGAN-V's FVD₁₆), each resized whole to 224 x 224
(bilinear, no antialiasing) and scaled from [0, 1] to [-1, 1].

These are DeepMind's released Kinetics-400 weights; the TF-hub module FVD is usually computed
with holds other weights (StyleGAN-V notes it), so the values rank models scored here and are
not those printed elsewhere.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from paradrive.scoring.networks import NetworkExtractor, as_frames

__all__ = ["InceptionI3d", "I3DFeatures", "CLIP_FRAMES", "INPUT_SIZE", "NUM_CLASSES"]

CLIP_FRAMES = 16
INPUT_SIZE = 224
NUM_CLASSES = 400

Triple = tuple[int, int, int]


def _same_padding(x: torch.Tensor, kernel: Triple, stride: Triple) -> torch.Tensor:
    """Zero-pad (B, C, T, H, W) as TF's SAME: per axis max(k − s, 0) when s divides the size, else
    max(k − size mod s, 0), the smaller half in front."""
    pads: list[int] = []
    for size, k, s in zip(reversed(x.shape[2:]), reversed(kernel), reversed(stride)):
        total = max(k - (s if size % s == 0 else size % s), 0)
        pads += [total // 2, total - total // 2]
    return F.pad(x, pads)


class Unit3D(nn.Module):
    """SAME-padded conv3d → batch norm (ε = 0.001) → ReLU; the logits unit has a bias, no norm,
    no activation."""

    def __init__(self, cin: int, cout: int, kernel: Triple = (1, 1, 1), stride: Triple = (1, 1, 1), *,
                 logits: bool = False):
        super().__init__()
        self.kernel, self.stride, self.is_logits = kernel, stride, logits
        self.conv3d = nn.Conv3d(cin, cout, kernel, stride=stride, padding=0, bias=logits)
        self.bn = None if logits else nn.BatchNorm3d(cout, eps=0.001, momentum=0.01)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.conv3d(_same_padding(x, self.kernel, self.stride))
        if self.bn is None:
            return x
        return F.relu(self.bn(x))


class MaxPoolSame(nn.Module):
    """Max pool padded as TF's SAME (zeros: inputs are after a ReLU, so it equals −∞ padding)."""

    def __init__(self, kernel: Triple, stride: Triple):
        super().__init__()
        self.kernel, self.stride = kernel, stride

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.max_pool3d(_same_padding(x, self.kernel, self.stride), self.kernel, self.stride)


class InceptionModule(nn.Module):
    """Four branches: 1x1 | 1x1→3x3x3 | 1x1→3x3x3 | max 3x3x3→1x1; widths ``w`` = (b0, b1a, b1b,
    b2a, b2b, b3b); out w[0] + w[2] + w[4] + w[5] channels."""

    def __init__(self, cin: int, w: tuple[int, int, int, int, int, int]):
        super().__init__()
        self.b0 = Unit3D(cin, w[0])
        self.b1a = Unit3D(cin, w[1])
        self.b1b = Unit3D(w[1], w[2], (3, 3, 3))
        self.b2a = Unit3D(cin, w[3])
        self.b2b = Unit3D(w[3], w[4], (3, 3, 3))
        self.b3a = MaxPoolSame((3, 3, 3), (1, 1, 1))
        self.b3b = Unit3D(cin, w[5])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([self.b0(x), self.b1b(self.b1a(x)), self.b2b(self.b2a(x)), self.b3b(self.b3a(x))], 1)


class InceptionI3d(nn.Module):
    """I3D, RGB stream. forward: (B, 3, T, H, W) in [-1, 1] (T = 16, 224 x 224 for FVD) -> (B, 400)
    logits averaged over the remaining time steps."""

    def __init__(self, num_classes: int = NUM_CLASSES):
        super().__init__()
        self.Conv3d_1a_7x7 = Unit3D(3, 64, (7, 7, 7), (2, 2, 2))
        self.MaxPool3d_2a_3x3 = MaxPoolSame((1, 3, 3), (1, 2, 2))
        self.Conv3d_2b_1x1 = Unit3D(64, 64)
        self.Conv3d_2c_3x3 = Unit3D(64, 192, (3, 3, 3))
        self.MaxPool3d_3a_3x3 = MaxPoolSame((1, 3, 3), (1, 2, 2))
        self.Mixed_3b = InceptionModule(192, (64, 96, 128, 16, 32, 32))
        self.Mixed_3c = InceptionModule(256, (128, 128, 192, 32, 96, 64))
        self.MaxPool3d_4a_3x3 = MaxPoolSame((3, 3, 3), (2, 2, 2))
        self.Mixed_4b = InceptionModule(480, (192, 96, 208, 16, 48, 64))
        self.Mixed_4c = InceptionModule(512, (160, 112, 224, 24, 64, 64))
        self.Mixed_4d = InceptionModule(512, (128, 128, 256, 24, 64, 64))
        self.Mixed_4e = InceptionModule(512, (112, 144, 288, 32, 64, 64))
        self.Mixed_4f = InceptionModule(528, (256, 160, 320, 32, 128, 128))
        self.MaxPool3d_5a_2x2 = MaxPoolSame((2, 2, 2), (2, 2, 2))
        self.Mixed_5b = InceptionModule(832, (256, 160, 320, 32, 128, 128))
        self.Mixed_5c = InceptionModule(832, (384, 192, 384, 48, 128, 128))
        self.logits = Unit3D(1024, num_classes, logits=True)

    def pooled(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3, T, H, W) -> (B, 1024, T', 1, 1): the (2, 7, 7) stride-1 average pool before the
        logits (clipped to the map for inputs below 9 frames or 193 pixels)."""
        for m in self.children():
            if m is not self.logits:
                x = m(x)
        kernel = (min(2, x.shape[2]), min(7, x.shape[3]), min(7, x.shape[4]))
        return F.avg_pool3d(x, kernel, stride=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.logits(self.pooled(x)).mean(dim=(2, 3, 4))


def preprocess(clip: torch.Tensor) -> torch.Tensor:
    """clip: (T, 3, H, W) in [0, 1] -> (1, 3, T, 224, 224) in [-1, 1]."""
    x = F.interpolate(clip, size=(INPUT_SIZE, INPUT_SIZE), mode="bilinear", align_corners=False)
    return (2.0 * x - 1.0).permute(1, 0, 2, 3).unsqueeze(0)


class I3DFeatures(NetworkExtractor):
    """FVD's extractor: (T, H, W, 3) uint8 frames, T >= 16 -> (1, 400) float64 logits of frames 0-15."""

    metric = "fvd"

    def build(self) -> nn.Module:
        return InceptionI3d()

    @torch.inference_mode()
    def features(self, frames: np.ndarray) -> np.ndarray:
        if len(frames) < CLIP_FRAMES:
            raise ValueError(f"FVD needs videos of at least {CLIP_FRAMES} frames, this one has {len(frames)}")
        clip = preprocess(as_frames(frames[:CLIP_FRAMES], self.device))
        return self.net(clip).double().cpu().numpy()
