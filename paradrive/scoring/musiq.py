"""IQ's network: MUSIQ, the multi-scale image quality transformer (Ke et al. 2021), as VBench's
imaging quality runs it, in plain torch with the parameter names of pyiqa's MUSIQ checkpoints
(``musiq_spaq_ckpt-358bb6af.pth``, VBench's; ``musiq_koniq_ckpt-e95806b9.pth`` has the same layout)
so those files load as they are published.

A frame becomes a sequence of 32 x 32 patches from three scales: the frame resized (aspect kept,
bicubic) to a longer side of 224 and of 384, each padded to its full square grid of patches
(ceil(L / 32)² with an input mask), and the frame at its own size, all its patches. Each patch
passes a ResNet stem (weight-standardised 7x7/2 convolution, group norm, 3x3/2 max pool, one
bottleneck; TF ``SAME`` padding), is embedded to 384-d, and gets a hash-based spatial embedding
(its row and column mapped onto a 10 x 10 grid) and a scale embedding; a 14-layer transformer
reads the sequence after a class token and a linear head turns that token into the score.

VBench's imaging quality (its ``longer`` mode): every frame whose longer side exceeds 512 pixels
is resized to a longer side of 512 (bilinear, no antialiasing, back to 8-bit), scaled to
[0, 1], then to [-1, 1] for MUSIQ; a video's IQ is the mean over its frames, on the 0-100 scale
the paper prints (VBench divides it by 100).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from paradrive.scoring.networks import NetworkExtractor, as_frames

__all__ = ["MUSIQ", "MusiqScores", "multiscale_patches", "vbench_resize", "PATCH", "SCALES",
           "HASH_GRID", "LONGER_SIDE", "BATCH"]

PATCH = 32
SCALES = (224, 384)     # longer sides of the resized scales; the frame's own size comes after
HASH_GRID = 10
LONGER_SIDE = 512       # VBench's ``longer`` mode
BATCH = 4               # frames per forward pass


def _same_pad(x: torch.Tensor, kernel: int, stride: int) -> torch.Tensor:
    """Zero-pad (B, C, H, W) as TF's SAME for a square kernel (the smaller half in front)."""
    pads: list[int] = []
    for size in (x.shape[-1], x.shape[-2]):
        total = max((math.ceil(size / stride) - 1) * stride + kernel - size, 0)
        pads += [total // 2, total - total // 2]
    return F.pad(x, pads)


class StdConv(nn.Conv2d):
    """Convolution with standardised weights (per output channel: zero mean, unit sample std,
    + 1e-5) and SAME padding."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        w = self.weight
        w = (w - w.mean(dim=(1, 2, 3), keepdim=True)) / (w.std(dim=(1, 2, 3), keepdim=True) + 1e-5)
        k, s = self.kernel_size[0], self.stride[0]
        return F.conv2d(_same_pad(x, k, s), w, self.bias, self.stride)


class Bottleneck(nn.Module):
    """1x1 → 3x3 → 1x1 weight-standardised convolutions with group norms (32 groups, ε = 1e-4)
    and a projected shortcut; (B, cin, H, W) -> (B, cout, H, W)."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.conv1 = StdConv(cin, cin, 1, 1, bias=False)
        self.gn1 = nn.GroupNorm(32, cin, eps=1e-4)
        self.conv2 = StdConv(cin, cin, 3, 1, bias=False)
        self.gn2 = nn.GroupNorm(32, cin, eps=1e-4)
        self.conv3 = StdConv(cin, cout, 1, 1, bias=False)
        self.gn3 = nn.GroupNorm(32, cout, eps=1e-4)
        self.conv_proj = StdConv(cin, cout, 1, 1, bias=False)
        self.gn_proj = nn.GroupNorm(32, cout, eps=1e-4)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        shortcut = self.gn_proj(self.conv_proj(x))
        y = F.relu(self.gn1(self.conv1(x)))
        y = F.relu(self.gn2(self.conv2(y)))
        return F.relu(self.gn3(self.conv3(y)) + shortcut)


class Attention(nn.Module):
    """Multi-head self-attention whose masked keys get −1000 before the softmax (MUSIQ's)."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.heads = heads
        self.query, self.key, self.value, self.out = (nn.Linear(dim, dim) for _ in range(4))

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        b, n, c = x.shape
        q, k, v = (m(x).reshape(b, n, self.heads, c // self.heads).transpose(1, 2)
                   for m in (self.query, self.key, self.value))
        logits = (q @ k.transpose(-2, -1)) * (c // self.heads) ** -0.5
        pair = mask[:, None, :, None] & mask[:, None, None, :]
        weights = logits.masked_fill(~pair, -1e3).softmax(dim=-1)
        return self.out((weights @ v).transpose(1, 2).reshape(b, n, c))


class Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1, self.fc2 = nn.Linear(dim, hidden), nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.gelu(self.fc1(x)))


class EncoderBlock(nn.Module):
    """Pre-norm transformer block (layer norms ε = 1e-6, exact GELU)."""

    def __init__(self, dim: int, mlp_dim: int, heads: int):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=1e-6)
        self.attention = Attention(dim, heads)
        self.norm2 = nn.LayerNorm(dim, eps=1e-6)
        self.mlp = Mlp(dim, mlp_dim)

    def forward(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        x = x + self.attention(self.norm1(x), mask)
        return x + self.mlp(self.norm2(x))


class HashPositions(nn.Module):
    def __init__(self, grid: int, dim: int):
        super().__init__()
        self.position_emb = nn.Parameter(torch.zeros(1, grid * grid, dim))


class ScaleEmbeddings(nn.Module):
    def __init__(self, scales: int, dim: int):
        super().__init__()
        self.scale_emb = nn.Parameter(torch.zeros(scales, dim))


class Encoder(nn.Module):
    """Adds the spatial and scale embeddings, prepends the class token, runs the blocks."""

    def __init__(self, dim: int, mlp_dim: int, heads: int, layers: int, scales: int, grid: int):
        super().__init__()
        self.posembed_input = HashPositions(grid, dim)
        self.scaleembed_input = ScaleEmbeddings(scales, dim)
        self.cls = nn.Parameter(torch.zeros(1, 1, dim))
        self.encoder_norm = nn.LayerNorm(dim, eps=1e-6)
        self.transformer = nn.ModuleDict({f"encoderblock_{i}": EncoderBlock(dim, mlp_dim, heads)
                                          for i in range(layers)})

    def forward(self, x: torch.Tensor, spatial: torch.Tensor, scale: torch.Tensor,
                mask: torch.Tensor) -> torch.Tensor:
        x = x + self.posembed_input.position_emb[0][spatial] + self.scaleembed_input.scale_emb[scale]
        x = torch.cat([self.cls.expand(x.shape[0], -1, -1), x], dim=1)
        mask = torch.cat([torch.ones_like(mask[:, :1]), mask], dim=1)
        for block in self.transformer.values():
            x = block(x, mask)
        return self.encoder_norm(x)


class MUSIQ(nn.Module):
    """MUSIQ with one output (the mean opinion score of KonIQ / SPAQ checkpoints).

    forward(patches (B, N, 3·32·32) in [-1, 1], spatial (B, N) hash index, scale (B, N) scale
    index, mask (B, N) bool) -> (B,) scores."""

    def __init__(self, hidden: int = 384, mlp_dim: int = 1152, heads: int = 6, layers: int = 14,
                 scales: int = len(SCALES) + 1, grid: int = HASH_GRID, stem: int = 64):
        super().__init__()
        self.conv_root = StdConv(3, stem, 7, 2, bias=False)
        self.gn_root = nn.GroupNorm(32, stem, eps=1e-6)
        self.block1 = Bottleneck(stem, stem * 4)
        self.embedding = nn.Linear(stem * 4 * (PATCH // 4) ** 2, hidden)
        self.transformer_encoder = Encoder(hidden, mlp_dim, heads, layers, scales, grid)
        self.head = nn.Linear(hidden, 1)

    def forward(self, patches: torch.Tensor, spatial: torch.Tensor, scale: torch.Tensor,
                mask: torch.Tensor) -> torch.Tensor:
        b, n, _ = patches.shape
        x = F.relu(self.gn_root(self.conv_root(patches.reshape(b * n, 3, PATCH, PATCH))))
        x = F.max_pool2d(_same_pad(x, 3, 2), 3, 2)
        x = self.block1(x)
        x = x.permute(0, 2, 3, 1).reshape(b, n, -1)   # (row, column, channel), the TF order
        x = self.transformer_encoder(self.embedding(x), spatial, scale, mask)
        return self.head(x[:, 0]).squeeze(-1)


def _hash_index(count: int, grid: int, device: torch.device) -> torch.Tensor:
    """The grid cell (0 … grid−1) of each of ``count`` patches along one side: nearest-neighbour
    resampling of 0 … grid−1 to ``count`` places."""
    cells = torch.arange(grid, dtype=torch.float32, device=device).reshape(1, 1, grid)
    return F.interpolate(cells, size=count, mode="nearest").reshape(count).long()


def _patches_of(image: torch.Tensor, scale_id: int, max_len: int | None, grid: int
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """image (B, 3, H, W) -> patches (B, N, 3·32·32), spatial (B, N), scale (B, N), mask (B, N):
    SAME-padded non-overlapping patches in row order, padded with masked zeros (or cut) to
    ``max_len`` when given."""
    b, _, h, w = image.shape
    rows, cols = math.ceil(h / PATCH), math.ceil(w / PATCH)
    p = F.unfold(_same_pad(image, PATCH, PATCH), PATCH, stride=PATCH).transpose(1, 2)
    dev = image.device
    spatial = (_hash_index(rows, grid, dev)[:, None] * grid + _hash_index(cols, grid, dev)[None, :]).reshape(-1)
    spatial = spatial.expand(b, -1)
    mask = torch.ones(b, rows * cols, dtype=torch.bool, device=dev)
    if max_len is not None:
        extra = max(max_len - rows * cols, 0)
        p = F.pad(p, (0, 0, 0, extra))[:, :max_len]
        spatial = F.pad(spatial, (0, extra))[:, :max_len]
        mask = F.pad(mask, (0, extra))[:, :max_len]
    scale = torch.where(mask, torch.full_like(spatial, scale_id), torch.zeros_like(spatial))
    return p, spatial, scale, mask


def multiscale_patches(image: torch.Tensor, grid: int = HASH_GRID
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """image: (B, 3, H, W) in [-1, 1] -> MUSIQ's inputs (patches, spatial, scale, mask) of the
    scales in :data:`SCALES` (each ceil(L/32)² long) followed by the image's own patches."""
    h, w = image.shape[-2:]
    parts = []
    for scale_id, longer in enumerate(sorted(SCALES)):
        ratio = longer / max(h, w)
        resized = F.interpolate(image, size=(round(h * ratio), round(w * ratio)), mode="bicubic",
                                align_corners=False)
        parts.append(_patches_of(resized, scale_id, math.ceil(longer / PATCH) ** 2, grid))
    parts.append(_patches_of(image, len(SCALES), None, grid))
    patches, spatial, scale, mask = (torch.cat(t, dim=1) for t in zip(*parts))
    return patches, spatial, scale, mask


def vbench_resize(frames: torch.Tensor) -> torch.Tensor:
    """frames: (B, 3, H, W) in [0, 1] -> the same, resized to a longer side of 512 when longer
    (bilinear, no antialiasing, rounded to 8-bit: VBench's ``longer`` mode)."""
    h, w = frames.shape[-2:]
    if max(h, w) <= LONGER_SIDE:
        return frames
    ratio = LONGER_SIDE / max(h, w)
    x = F.interpolate(frames * 255.0, size=(int(ratio * h), int(ratio * w)), mode="bilinear", align_corners=False)
    return x.round().clamp(0, 255) / 255.0


class MusiqScores(NetworkExtractor):
    """IQ's extractor: (T, H, W, 3) uint8 frames -> (T,) float64 MUSIQ scores (0-100), every frame."""

    metric = "iq"

    def build(self) -> nn.Module:
        return MUSIQ()

    @torch.inference_mode()
    def features(self, frames: np.ndarray) -> np.ndarray:
        out = []
        for i in range(0, len(frames), BATCH):
            x = vbench_resize(as_frames(frames[i:i + BATCH], self.device))
            out.append(self.net(*multiscale_patches(2.0 * x - 1.0)).double().cpu().numpy())
        return np.concatenate(out) if out else np.zeros((0,))
