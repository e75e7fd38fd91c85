"""RAFT optical flow (Teed & Deng, "RAFT: Recurrent All-Pairs Field Transforms for Optical Flow",
ECCV 2020) for TCE, from the weights files of its original release (``raft-things.pth``,
``raft-sintel.pth``, ``raft-kitti.pth``, ``raft-chairs.pth``: the basic model; ``raft-small.pth``:
the small one), in plain torch.

The network, as published: a feature encoder (``fnet``, instance norm) and a context encoder
(``cnet``, batch norm; none in the small model) at 1/8 of the frame, the all-pairs correlation of
the two frames' features (dot products / sqrt(dim)) pooled into a 4-level pyramid, and a recurrent
update (``update_block``: motion encoder, separable ConvGRU, flow head) that reads a (2r + 1)^2
window of every level around the current match (r = 4; small: 3) and adds a flow step; the 1/8
flow is upsampled by a learned convex combination of 3x3 neighbours (small: bilinear).
Frames are padded to multiples of 8 by repeating their edge pixels, evenly on both sides as the
release's ``InputPadder`` does, and the flow is cut back to the frame.

SEA-RAFT's weights are another network (a ResNet-FPN encoder, a flow head outside the update
block) and are refused, as is any file whose tensors are not one of these two layouts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from paradrive.errors import ConfigError
from paradrive.scoring.flow import FlowSettings, dis_flow
from paradrive.scoring.networks import PUBLISHED_AT, Weights, load_into, load_state_dict, weights_sha256
from paradrive.scoring.networks import _refuse as refuse_weights

if TYPE_CHECKING:
    from paradrive.scoring.flow import Flow

__all__ = ["RAFT_ITERATIONS", "RaftShape", "Raft", "check_flow_weights", "raft_settings", "load_raft",
           "raft_flow", "flow_of", "all_pairs_correlation", "lookup", "convex_upsample", "pad_to_8",
           "bilinear"]

# update iterations per flow: RAFT's own default (its forward pass); its demo runs 20, its Sintel
# evaluation 32
RAFT_ITERATIONS = 12

# a tensor every file of that layout holds (after the ``module.`` prefix is stripped)
_BASIC_KEY = "update_block.mask.0.weight"
_SMALL_KEY = "update_block.gru.convz.weight"
_SEA_RAFT_KEYS = ("upsample_weight.0.weight", "init_conv.weight")


@dataclass(frozen=True)
class RaftShape:
    """The sizes of one RAFT variant (the release's ``--small`` switch)."""

    variant: str            # "basic" or "small"
    hidden: int             # GRU state channels
    context: int            # context feature channels
    features: int           # correlation feature channels
    widths: tuple[int, int, int]   # encoder stage widths
    radius: int             # correlation window radius, per level
    levels: int = 4         # correlation pyramid levels

    @property
    def window(self) -> int:
        return self.levels * (2 * self.radius + 1) ** 2


BASIC = RaftShape("basic", hidden=128, context=128, features=256, widths=(64, 96, 128), radius=4)
SMALL = RaftShape("small", hidden=96, context=64, features=128, widths=(32, 64, 96), radius=3)


# ---- network -------------------------------------------------------------------------------------

def _norm(kind: str, channels: int) -> nn.Module:
    if kind == "batch":
        return nn.BatchNorm2d(channels)
    if kind == "instance":
        return nn.InstanceNorm2d(channels)   # no parameters, as released
    return nn.Identity()


class _Block(nn.Module):
    """A residual block: two 3x3 convolutions (``bottleneck``: 1x1, 3x3, 1x1 at a quarter of the
    width), the first strided, and a strided 1x1 shortcut when the size changes."""

    def __init__(self, cin: int, cout: int, norm: str, stride: int, bottleneck: bool):
        super().__init__()
        if bottleneck:
            mid = cout // 4
            self.conv1 = nn.Conv2d(cin, mid, 1)
            self.conv2 = nn.Conv2d(mid, mid, 3, padding=1, stride=stride)
            self.conv3 = nn.Conv2d(mid, cout, 1)
            self.norm1, self.norm2, self.norm3 = _norm(norm, mid), _norm(norm, mid), _norm(norm, cout)
            convs = [(self.conv1, self.norm1), (self.conv2, self.norm2), (self.conv3, self.norm3)]
        else:
            self.conv1 = nn.Conv2d(cin, cout, 3, padding=1, stride=stride)
            self.conv2 = nn.Conv2d(cout, cout, 3, padding=1)
            self.norm1, self.norm2 = _norm(norm, cout), _norm(norm, cout)
            convs = [(self.conv1, self.norm1), (self.conv2, self.norm2)]
        self._convs = convs
        self.downsample: nn.Module | None = None
        if stride != 1:
            # the shortcut's norm is registered twice in the release (norm3 / norm4 and
            # downsample.1): both names are in its files
            shortcut_norm = _norm(norm, cout)
            setattr(self, "norm4" if bottleneck else "norm3", shortcut_norm)
            self.downsample = nn.Sequential(nn.Conv2d(cin, cout, 1, stride=stride), shortcut_norm)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = x
        for conv, norm in self._convs:
            y = F.relu(norm(conv(y)))
        return F.relu((x if self.downsample is None else self.downsample(x)) + y)


class _Encoder(nn.Module):
    """(N, 3, H, W) in [-1, 1] -> (N, out, H/8, W/8): a 7x7 stride-2 convolution, three stages of
    two residual blocks (strides 1, 2, 2), a 1x1 projection."""

    def __init__(self, shape: RaftShape, out: int, norm: str):
        super().__init__()
        bottleneck = shape.variant == "small"
        w1, w2, w3 = shape.widths
        self.conv1 = nn.Conv2d(3, w1, 7, stride=2, padding=3)
        self.norm1 = _norm(norm, w1)

        def stage(cin: int, cout: int, stride: int) -> nn.Sequential:
            return nn.Sequential(_Block(cin, cout, norm, stride, bottleneck),
                                 _Block(cout, cout, norm, 1, bottleneck))

        self.layer1, self.layer2, self.layer3 = stage(w1, w1, 1), stage(w1, w2, 2), stage(w2, w3, 2)
        self.conv2 = nn.Conv2d(w3, out, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.relu(self.norm1(self.conv1(x)))
        return self.conv2(self.layer3(self.layer2(self.layer1(x))))


class _MotionEncoder(nn.Module):
    """(flow (N, 2, h, w), correlation window (N, window, h, w)) -> motion features whose last two
    channels are the flow itself."""

    def __init__(self, shape: RaftShape):
        super().__init__()
        self.small = shape.variant == "small"
        if self.small:
            self.convc1 = nn.Conv2d(shape.window, 96, 1)
            self.convf1 = nn.Conv2d(2, 64, 7, padding=3)
            self.convf2 = nn.Conv2d(64, 32, 3, padding=1)
            self.conv = nn.Conv2d(128, 80, 3, padding=1)
        else:
            self.convc1 = nn.Conv2d(shape.window, 256, 1)
            self.convc2 = nn.Conv2d(256, 192, 3, padding=1)
            self.convf1 = nn.Conv2d(2, 128, 7, padding=3)
            self.convf2 = nn.Conv2d(128, 64, 3, padding=1)
            self.conv = nn.Conv2d(64 + 192, 128 - 2, 3, padding=1)

    def forward(self, flow: torch.Tensor, corr: torch.Tensor) -> torch.Tensor:
        c = F.relu(self.convc1(corr))
        if not self.small:
            c = F.relu(self.convc2(c))
        f = F.relu(self.convf2(F.relu(self.convf1(flow))))
        return torch.cat([F.relu(self.conv(torch.cat([c, f], dim=1))), flow], dim=1)


def _gru_step(h: torch.Tensor, x: torch.Tensor, z_conv: nn.Module, r_conv: nn.Module,
              q_conv: nn.Module) -> torch.Tensor:
    hx = torch.cat([h, x], dim=1)
    z, r = torch.sigmoid(z_conv(hx)), torch.sigmoid(r_conv(hx))
    q = torch.tanh(q_conv(torch.cat([r * h, x], dim=1)))
    return (1 - z) * h + z * q


class _Gru(nn.Module):
    """A convolutional GRU: 3x3 gates (small), or a 1x5 then a 5x1 pass (basic)."""

    def __init__(self, hidden: int, inputs: int, separable: bool):
        super().__init__()
        c = hidden + inputs
        self.separable = separable
        if separable:
            for suffix, k, p in (("1", (1, 5), (0, 2)), ("2", (5, 1), (2, 0))):
                for gate in "zrq":
                    setattr(self, f"conv{gate}{suffix}", nn.Conv2d(c, hidden, k, padding=p))
        else:
            self.convz, self.convr, self.convq = (nn.Conv2d(c, hidden, 3, padding=1) for _ in range(3))

    def forward(self, h: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        passes = ("1", "2") if self.separable else ("",)
        for s in passes:
            h = _gru_step(h, x, getattr(self, f"convz{s}"), getattr(self, f"convr{s}"),
                          getattr(self, f"convq{s}"))
        return h


class _FlowHead(nn.Module):
    def __init__(self, cin: int, hidden: int):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, hidden, 3, padding=1)
        self.conv2 = nn.Conv2d(hidden, 2, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv2(F.relu(self.conv1(x)))


class _Update(nn.Module):
    """One refinement: (state, context, correlation window, flow) -> (state, upsampling mask
    logits (N, 576, h, w) or None, flow step (N, 2, h, w))."""

    def __init__(self, shape: RaftShape):
        super().__init__()
        small = shape.variant == "small"
        motion = 82 if small else 128
        self.encoder = _MotionEncoder(shape)
        self.gru = _Gru(shape.hidden, shape.context + motion, separable=not small)
        self.flow_head = _FlowHead(shape.hidden, 128 if small else 256)
        self.mask: nn.Module | None = None
        if not small:
            self.mask = nn.Sequential(nn.Conv2d(shape.hidden, 256, 3, padding=1), nn.ReLU(),
                                      nn.Conv2d(256, 64 * 9, 1))

    def forward(self, h: torch.Tensor, context: torch.Tensor, corr: torch.Tensor,
                flow: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
        h = self.gru(h, torch.cat([context, self.encoder(flow, corr)], dim=1))
        mask = None if self.mask is None else 0.25 * self.mask(h)   # the release's scale
        return h, mask, self.flow_head(h)


class Raft(nn.Module):
    """RAFT with the release's parameter names (``fnet``, ``cnet``, ``update_block``)."""

    def __init__(self, shape: RaftShape = BASIC):
        super().__init__()
        self.shape = shape
        small = shape.variant == "small"
        self.fnet = _Encoder(shape, shape.features, "instance")
        self.cnet = _Encoder(shape, shape.hidden + shape.context, "none" if small else "batch")
        self.update_block = _Update(shape)

    def forward(self, image1: torch.Tensor, image2: torch.Tensor,
                iterations: int = RAFT_ITERATIONS) -> torch.Tensor:
        """image1, image2: (N, 3, H, W) float RGB in [0, 255], H and W multiples of 8 ->
        (N, 2, H, W) flow from image1 to image2, pixels (dx, dy)."""
        n = image1.shape[0]
        x1, x2 = 2 * (image1 / 255.0) - 1, 2 * (image2 / 255.0) - 1
        f1, f2 = self.fnet(torch.cat([x1, x2], dim=0)).float().split([n, n], dim=0)
        pyramid = correlation_pyramid(all_pairs_correlation(f1, f2), self.shape.levels)
        h, context = self.cnet(x1).split([self.shape.hidden, self.shape.context], dim=1)
        h, context = torch.tanh(h), torch.relu(context)
        h8, w8 = f1.shape[-2:]
        flow = torch.zeros((n, 2, h8, w8), dtype=torch.float32, device=f1.device)
        grid = pixel_grid(h8, w8, device=f1.device)
        mask = None
        for _ in range(iterations):
            corr = lookup(pyramid, grid + flow, self.shape.radius)
            h, mask, step = self.update_block(h, context, corr, flow)
            flow = flow + step
        if mask is None:
            up = (8 * flow.shape[-2], 8 * flow.shape[-1])
            return 8 * F.interpolate(flow, size=up, mode="bilinear", align_corners=True)
        return convex_upsample(flow, mask)


# ---- the pieces, as pure functions --------------------------------------------------------------

def pixel_grid(h: int, w: int, device: torch.device) -> torch.Tensor:
    """(1, 2, h, w): every pixel's own (x, y)."""
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float32, device=device),
                            torch.arange(w, dtype=torch.float32, device=device), indexing="ij")
    return torch.stack([xs, ys])[None]


def all_pairs_correlation(f1: torch.Tensor, f2: torch.Tensor) -> torch.Tensor:
    """f1, f2: (N, D, h, w) features -> (N * h * w, h, w): for every pixel of f1, its dot product
    with every pixel of f2, over sqrt(D)."""
    n, d, h, w = f1.shape
    corr = torch.einsum("ndp,ndq->npq", f1.reshape(n, d, h * w), f2.reshape(n, d, h * w))
    return corr.reshape(n * h * w, h, w) / math.sqrt(d)


def correlation_pyramid(corr: torch.Tensor, levels: int) -> list[torch.Tensor]:
    """(P, h, w) -> ``levels`` maps, each the previous one 2x2 average-pooled."""
    out = [corr]
    for _ in range(levels - 1):
        out.append(F.avg_pool2d(out[-1][:, None], 2, stride=2)[:, 0])
    return out


def bilinear(maps: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """maps: (P, H, W); points: (P, K, 2) pixel (x, y) on map p -> (P, K) bilinear samples, zero
    outside the map (a 1-pixel map is sampled as well)."""
    p, hh, ww = maps.shape
    flat = maps.reshape(p, hh * ww)
    x, y = points[..., 0], points[..., 1]
    x0, y0 = torch.floor(x), torch.floor(y)
    ax, ay = x - x0, y - y0
    out = torch.zeros(points.shape[:2], dtype=maps.dtype, device=maps.device)
    for dx, dy, weight in ((0, 0, (1 - ax) * (1 - ay)), (1, 0, ax * (1 - ay)),
                           (0, 1, (1 - ax) * ay), (1, 1, ax * ay)):
        xi, yi = x0 + dx, y0 + dy
        inside = (xi >= 0) & (xi <= ww - 1) & (yi >= 0) & (yi <= hh - 1)
        index = (yi.clamp(0, hh - 1) * ww + xi.clamp(0, ww - 1)).long()
        out = out + torch.where(inside, weight * flat.gather(1, index), 0.0)
    return out


def lookup(pyramid: list[torch.Tensor], coords: torch.Tensor, radius: int) -> torch.Tensor:
    """The correlation window around each pixel's match: pyramid of (N * h * w, h_l, w_l) maps,
    coords (N, 2, h, w) the match (x, y) at level 0 -> (N, levels * (2r + 1)^2, h, w). Level l is
    read at coords / 2^l + (i - r, j - r), channel l * (2r + 1)^2 + i * (2r + 1) + j: the first
    offset moves x, as in the release (its weights depend on the order)."""
    n, _, h, w = coords.shape
    d = torch.arange(-radius, radius + 1, dtype=torch.float32, device=coords.device)
    di, dj = torch.meshgrid(d, d, indexing="ij")
    offsets = torch.stack([di, dj], dim=-1).reshape(1, -1, 2)      # (1, K, 2): (dx, dy)
    centre = coords.permute(0, 2, 3, 1).reshape(n * h * w, 1, 2)
    windows = [bilinear(level, centre / 2 ** i + offsets) for i, level in enumerate(pyramid)]
    return torch.cat(windows, dim=1).reshape(n, h, w, -1).permute(0, 3, 1, 2).contiguous()


def convex_upsample(flow: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """flow (N, 2, h, w) at 1/8, mask logits (N, 9 * 64, h, w) -> (N, 2, 8h, 8w): each of the 64
    sub-pixels of a pixel is a softmax-weighted mean of 8 x the flow of that pixel's 3x3
    neighbourhood (zero beyond the border). Mask channel k * 64 + a * 8 + b: neighbour k
    (row-major in the 3x3), sub-pixel row a, column b."""
    n, _, h, w = flow.shape
    weights = torch.softmax(mask.reshape(n, 9, 8, 8, h, w), dim=1)
    neighbours = F.unfold(8 * flow, kernel_size=3, padding=1).reshape(n, 2, 9, h, w)
    up = torch.einsum("nkabhw,nckhw->nchawb", weights, neighbours)
    return up.reshape(n, 2, 8 * h, 8 * w)


def pad_to_8(x: torch.Tensor) -> tuple[torch.Tensor, tuple[int, int, int, int]]:
    """(N, C, H, W) -> edge-padded to multiples of 8, half of the padding on each side (the odd
    pixel right / below), and the (left, right, top, bottom) padding to cut off again."""
    hh, ww = x.shape[-2:]
    ph, pw = -hh % 8, -ww % 8
    pad = (pw // 2, pw - pw // 2, ph // 2, ph - ph // 2)
    return (F.pad(x, pad, mode="replicate") if ph or pw else x), pad


def unpad(x: torch.Tensor, pad: tuple[int, int, int, int]) -> torch.Tensor:
    """The inverse of :func:`pad_to_8` on a (..., H, W) tensor."""
    left, right, top, bottom = pad
    return x[..., top:x.shape[-2] - bottom, left:x.shape[-1] - right]


# ---- weights, settings and the flow callable -----------------------------------------------------

def _refuse(path: object, what: str) -> ConfigError:
    return refuse_weights("flow", path, what)   # the feature metrics' wording: "--flow-weights …"


def _shape_of(state: dict[str, Any], path: Path) -> RaftShape:
    if _BASIC_KEY in state:
        return BASIC
    if _SMALL_KEY in state:
        return SMALL
    if any(k in state for k in _SEA_RAFT_KEYS):
        raise _refuse(path, "SEA-RAFT's weights, another architecture (ResNet-FPN encoders, "
                            "'upsample_weight' outside the update block) than RAFT's, which this "
                            "TCE runs")
    raise _refuse(path, f"not RAFT's weights (no {_BASIC_KEY!r} nor {_SMALL_KEY!r} among its "
                        f"{len(state)} tensors)")


def check_flow_weights(path: Path | str) -> Weights:
    """The RAFT weights at ``path``, checked (read, their layout named, loaded strictly into the
    network) before any video is read: ConfigError, one line naming the file and where RAFT's
    weights are published, for a missing, unreadable or other network's file."""
    path = Path(path).expanduser()
    if not path.exists():
        raise _refuse(path, "no such file")
    if not path.is_file():
        raise _refuse(path, "not a file")
    weights = Weights(metric="flow", path=path, published_at=PUBLISHED_AT["flow"])
    _load(weights, torch.device("cpu"))
    return weights


def _load(weights: Weights, device: torch.device) -> Raft:
    net = Raft(_shape_of(load_state_dict(weights), weights.path))
    load_into(net, weights)
    return net.eval().to(device)


def raft_settings(path: Path | str, settings: FlowSettings = FlowSettings()) -> FlowSettings:
    """The TCE settings that run RAFT from the weights file at ``path`` (checked): the method
    ``raft-<first 12 hex of the file's SHA-256>-<iterations>it``, so that cached results of DIS, of
    other weights and of other iteration counts stay apart."""
    weights = check_flow_weights(path)
    return replace(settings, method=f"raft-{weights_sha256(weights)[:12]}-{RAFT_ITERATIONS}it",
                   weights=weights.path)


def load_raft(path: Path | str, device: torch.device) -> Raft:
    """The RAFT of the weights file at ``path`` (checked), in eval mode on ``device``."""
    return _load(check_flow_weights(path), device)


def raft_flow(model: Raft, device: torch.device, iterations: int = RAFT_ITERATIONS) -> Flow:
    """A :data:`~paradrive.scoring.flow.Flow` of ``model`` on ``device``: (a, b) uint8 (H, W, 3)
    RGB frames -> float32 (H, W, 2) flow from a to b, pixels (dx, dy)."""

    def flow(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        if a.shape != b.shape or a.ndim != 3 or a.shape[-1] != 3:
            raise ValueError(f"RAFT takes two (H, W, 3) frames of one size, got {a.shape} and {b.shape}")
        if min(a.shape[:2]) <= 56:   # padded to 64 or more: 1/8 of it pooled 3 times keeps a pixel
            raise ValueError(f"a {a.shape[1]}x{a.shape[0]} frame is too small for RAFT's 4-level "
                             f"correlation pyramid (57 px or more a side)")
        pair = torch.as_tensor(np.stack([a, b]), device=device).permute(0, 3, 1, 2).float()
        padded, pad = pad_to_8(pair)
        with torch.inference_mode():
            out = model(padded[:1], padded[1:], iterations=iterations)
        return unpad(out, pad)[0].permute(1, 2, 0).cpu().numpy().astype(np.float32)

    return flow


def flow_of(settings: FlowSettings, device: str) -> Flow:
    """The flow ``settings`` ask for: RAFT from ``settings.weights`` on ``device`` (``auto``:
    CUDA when present), else OpenCV's DIS."""
    if settings.weights is None:
        return dis_flow
    from paradrive.devices import resolve_device

    where = resolve_device(device)
    return raft_flow(load_raft(settings.weights, where), where)
