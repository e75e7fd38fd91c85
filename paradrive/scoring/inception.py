"""FID's network: Inception-v3 as the TF FID graph has it (Szegedy et al. 2016; Heusel et al. 2017),
in plain torch, with the parameter names of pytorch-fid's ``pt_inception-2015-12-05-6726825d.pth``
so that file loads as it is published.

It differs from the ImageNet Inception-v3 as pytorch-fid's FID variant does: 1008 classes, the
average pools of the A, C and first E blocks ignore the zero padding (TF's pooling), and the
last E block pools its fourth branch by max instead of average. Features are the 2048-d output
of the final average pool.

Frames are resized to 299 x 299 (bilinear, no antialiasing, ``align_corners=False``, as
pytorch-fid's ``resize_input``) and scaled from [0, 1] to [-1, 1]; every frame of a video is a
sample (FID over frames).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from paradrive.scoring.networks import NetworkExtractor, as_frames

__all__ = ["FIDInceptionV3", "InceptionFeatures", "INPUT_SIZE", "FEATURE_DIM", "BATCH"]

INPUT_SIZE = 299
FEATURE_DIM = 2048
BATCH = 32   # frames per forward pass


class BasicConv2d(nn.Module):
    """conv (no bias) → batch norm (ε = 0.001, TF's) → ReLU."""

    def __init__(self, cin: int, cout: int, kernel: int | tuple[int, int],
                 padding: int | tuple[int, int] = 0, stride: int = 1):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, kernel, stride=stride, padding=padding, bias=False)
        self.bn = nn.BatchNorm2d(cout, eps=0.001)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(self.bn(self.conv(x)))


def _tf_avg_pool(x: torch.Tensor) -> torch.Tensor:
    """3 x 3 stride-1 average that, as TF's, leaves the zero padding out of the mean."""
    return F.avg_pool2d(x, kernel_size=3, stride=1, padding=1, count_include_pad=False)


class BlockA(nn.Module):
    """Mixed_5b/c/d: 1x1 | 1x1→5x5 | 1x1→3x3→3x3 | avg→1x1; out 224 + pool_features."""

    def __init__(self, cin: int, pool_features: int):
        super().__init__()
        self.branch1x1 = BasicConv2d(cin, 64, 1)
        self.branch5x5_1 = BasicConv2d(cin, 48, 1)
        self.branch5x5_2 = BasicConv2d(48, 64, 5, padding=2)
        self.branch3x3dbl_1 = BasicConv2d(cin, 64, 1)
        self.branch3x3dbl_2 = BasicConv2d(64, 96, 3, padding=1)
        self.branch3x3dbl_3 = BasicConv2d(96, 96, 3, padding=1)
        self.branch_pool = BasicConv2d(cin, pool_features, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b5 = self.branch5x5_2(self.branch5x5_1(x))
        b3 = self.branch3x3dbl_3(self.branch3x3dbl_2(self.branch3x3dbl_1(x)))
        return torch.cat([self.branch1x1(x), b5, b3, self.branch_pool(_tf_avg_pool(x))], 1)


class BlockB(nn.Module):
    """Mixed_6a, the 35→17 grid reduction: 3x3/2 | 1x1→3x3→3x3/2 | max/2; out 768."""

    def __init__(self, cin: int):
        super().__init__()
        self.branch3x3 = BasicConv2d(cin, 384, 3, stride=2)
        self.branch3x3dbl_1 = BasicConv2d(cin, 64, 1)
        self.branch3x3dbl_2 = BasicConv2d(64, 96, 3, padding=1)
        self.branch3x3dbl_3 = BasicConv2d(96, 96, 3, stride=2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b3 = self.branch3x3dbl_3(self.branch3x3dbl_2(self.branch3x3dbl_1(x)))
        return torch.cat([self.branch3x3(x), b3, F.max_pool2d(x, 3, stride=2)], 1)


# (kernel, padding) of the factorised 7x7: one row, one column
_ROW: tuple[tuple[int, int], tuple[int, int]] = ((1, 7), (0, 3))
_COL: tuple[tuple[int, int], tuple[int, int]] = ((7, 1), (3, 0))


class BlockC(nn.Module):
    """Mixed_6b..e: factorised 7x7 convolutions (1x7 and 7x1) of width ``c7``; out 768."""

    def __init__(self, cin: int, c7: int):
        super().__init__()
        self.branch1x1 = BasicConv2d(cin, 192, 1)
        self.branch7x7_1 = BasicConv2d(cin, c7, 1)
        self.branch7x7_2 = BasicConv2d(c7, c7, *_ROW)
        self.branch7x7_3 = BasicConv2d(c7, 192, *_COL)
        self.branch7x7dbl_1 = BasicConv2d(cin, c7, 1)
        self.branch7x7dbl_2 = BasicConv2d(c7, c7, *_COL)
        self.branch7x7dbl_3 = BasicConv2d(c7, c7, *_ROW)
        self.branch7x7dbl_4 = BasicConv2d(c7, c7, *_COL)
        self.branch7x7dbl_5 = BasicConv2d(c7, 192, *_ROW)
        self.branch_pool = BasicConv2d(cin, 192, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b7 = self.branch7x7_3(self.branch7x7_2(self.branch7x7_1(x)))
        d = x
        for conv in (self.branch7x7dbl_1, self.branch7x7dbl_2, self.branch7x7dbl_3, self.branch7x7dbl_4,
                     self.branch7x7dbl_5):
            d = conv(d)
        return torch.cat([self.branch1x1(x), b7, d, self.branch_pool(_tf_avg_pool(x))], 1)


class BlockD(nn.Module):
    """Mixed_7a, the 17→8 grid reduction: 1x1→3x3/2 | 1x1→1x7→7x1→3x3/2 | max/2; out 1280."""

    def __init__(self, cin: int):
        super().__init__()
        self.branch3x3_1 = BasicConv2d(cin, 192, 1)
        self.branch3x3_2 = BasicConv2d(192, 320, 3, stride=2)
        self.branch7x7x3_1 = BasicConv2d(cin, 192, 1)
        self.branch7x7x3_2 = BasicConv2d(192, 192, (1, 7), padding=(0, 3))
        self.branch7x7x3_3 = BasicConv2d(192, 192, (7, 1), padding=(3, 0))
        self.branch7x7x3_4 = BasicConv2d(192, 192, 3, stride=2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b3 = self.branch3x3_2(self.branch3x3_1(x))
        b7 = self.branch7x7x3_4(self.branch7x7x3_3(self.branch7x7x3_2(self.branch7x7x3_1(x))))
        return torch.cat([b3, b7, F.max_pool2d(x, 3, stride=2)], 1)


class BlockE(nn.Module):
    """Mixed_7b/c: expanded 3x3 branches (1x3 and 3x1 side by side); out 2048. ``max_pool``: the
    FID graph's last block pools its fourth branch by max, the one before by TF's average."""

    def __init__(self, cin: int, *, max_pool: bool):
        super().__init__()
        self.max_pool = max_pool
        self.branch1x1 = BasicConv2d(cin, 320, 1)
        self.branch3x3_1 = BasicConv2d(cin, 384, 1)
        self.branch3x3_2a = BasicConv2d(384, 384, (1, 3), padding=(0, 1))
        self.branch3x3_2b = BasicConv2d(384, 384, (3, 1), padding=(1, 0))
        self.branch3x3dbl_1 = BasicConv2d(cin, 448, 1)
        self.branch3x3dbl_2 = BasicConv2d(448, 384, 3, padding=1)
        self.branch3x3dbl_3a = BasicConv2d(384, 384, (1, 3), padding=(0, 1))
        self.branch3x3dbl_3b = BasicConv2d(384, 384, (3, 1), padding=(1, 0))
        self.branch_pool = BasicConv2d(cin, 192, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        s = self.branch3x3_1(x)
        b3 = torch.cat([self.branch3x3_2a(s), self.branch3x3_2b(s)], 1)
        d = self.branch3x3dbl_2(self.branch3x3dbl_1(x))
        bd = torch.cat([self.branch3x3dbl_3a(d), self.branch3x3dbl_3b(d)], 1)
        pooled = F.max_pool2d(x, 3, stride=1, padding=1) if self.max_pool else _tf_avg_pool(x)
        return torch.cat([self.branch1x1(x), b3, bd, self.branch_pool(pooled)], 1)


class FIDInceptionV3(nn.Module):
    """The FID Inception-v3. forward: (B, 3, H, W) in [-1, 1] (299 x 299 for the published
    statistics) -> (B, 2048) final-average-pool features. ``fc`` (1008 classes) is kept so the
    published file loads whole; FID does not use it."""

    def __init__(self) -> None:
        super().__init__()
        self.Conv2d_1a_3x3 = BasicConv2d(3, 32, 3, stride=2)
        self.Conv2d_2a_3x3 = BasicConv2d(32, 32, 3)
        self.Conv2d_2b_3x3 = BasicConv2d(32, 64, 3, padding=1)
        self.Conv2d_3b_1x1 = BasicConv2d(64, 80, 1)
        self.Conv2d_4a_3x3 = BasicConv2d(80, 192, 3)
        self.Mixed_5b = BlockA(192, 32)
        self.Mixed_5c = BlockA(256, 64)
        self.Mixed_5d = BlockA(288, 64)
        self.Mixed_6a = BlockB(288)
        self.Mixed_6b = BlockC(768, 128)
        self.Mixed_6c = BlockC(768, 160)
        self.Mixed_6d = BlockC(768, 160)
        self.Mixed_6e = BlockC(768, 192)
        self.Mixed_7a = BlockD(768)
        self.Mixed_7b = BlockE(1280, max_pool=False)
        self.Mixed_7c = BlockE(2048, max_pool=True)
        self.fc = nn.Linear(2048, 1008)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.Conv2d_2b_3x3(self.Conv2d_2a_3x3(self.Conv2d_1a_3x3(x)))
        x = F.max_pool2d(x, 3, stride=2)
        x = F.max_pool2d(self.Conv2d_4a_3x3(self.Conv2d_3b_1x1(x)), 3, stride=2)
        for block in (self.Mixed_5b, self.Mixed_5c, self.Mixed_5d, self.Mixed_6a, self.Mixed_6b,
                      self.Mixed_6c, self.Mixed_6d, self.Mixed_6e, self.Mixed_7a, self.Mixed_7b, self.Mixed_7c):
            x = block(x)
        return x.mean(dim=(2, 3))


def preprocess(frames: torch.Tensor) -> torch.Tensor:
    """frames: (B, 3, H, W) in [0, 1] -> (B, 3, 299, 299) in [-1, 1] (pytorch-fid's resize and scale)."""
    x = F.interpolate(frames, size=(INPUT_SIZE, INPUT_SIZE), mode="bilinear", align_corners=False)
    return 2.0 * x - 1.0


class InceptionFeatures(NetworkExtractor):
    """FID's extractor: (T, H, W, 3) uint8 frames -> (T, 2048) float64 pool features, every frame."""

    metric = "fid"

    def build(self) -> nn.Module:
        return FIDInceptionV3()

    @torch.inference_mode()
    def features(self, frames: np.ndarray) -> np.ndarray:
        out = [self.net(preprocess(as_frames(frames[i:i + BATCH], self.device))).double().cpu().numpy()
               for i in range(0, len(frames), BATCH)]
        return np.concatenate(out, axis=0) if out else np.zeros((0, FEATURE_DIM))
