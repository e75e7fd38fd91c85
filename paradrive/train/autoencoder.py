"""Video autoencoders for the reference trainer: a pluggable protocol and a fixed CPU patch codec.

The paper diffuses in the latent space of Wan2.1's 3D VAE (4x temporal, 8x spatial compression,
16 channels). That VAE needs a GPU and its weights; the reference trainer instead ships a *fixed*
patch codec with the same shape contract, so the whole two-stage recipe runs and is tested on a
CPU. A real 3D VAE replaces it by implementing :class:`VideoEncoder` and being named in the
training config (``autoencoder.kind: "package.module:Factory"``).
"""

from __future__ import annotations

import importlib
import math
from typing import Any, Protocol, runtime_checkable
from collections.abc import Mapping

import torch
import torch.nn as nn


@runtime_checkable
class VideoEncoder(Protocol):
    """What the trainer needs from a video autoencoder.

    ``encode``: video (B, F, 3, H, W) in [-1, 1] -> latents (B, f, c, h, w).
    ``decode``: latents (B, f, c, h, w) -> video (B, F, 3, H, W), roughly in [-1, 1].
    ``latent_shape(F, H, W)``: the (f, c, h, w) that ``encode`` gives for such a video.
    ``frame_groups(F)``: for each latent frame, the index of the video frame whose camera pose
    stands for it (for 4x temporal compression every 4th frame, 0, 4, ..., 120 for 121 frames: one
    per Wan latent frame, as ReCamMaster-style trainers take poses).
    """

    latent_channels: int

    def encode(self, video: torch.Tensor) -> torch.Tensor: ...

    def decode(self, latents: torch.Tensor) -> torch.Tensor: ...

    def latent_shape(self, frames: int, height: int, width: int) -> tuple[int, int, int, int]: ...

    def frame_groups(self, frames: int) -> list[int]: ...


def _dct_matrix(n: int) -> torch.Tensor:
    """Orthonormal DCT-II basis, rows = frequencies: (n, n)."""
    k = torch.arange(n, dtype=torch.float64)[:, None]
    i = torch.arange(n, dtype=torch.float64)[None, :]
    m = torch.cos(math.pi * (2 * i + 1) * k / (2 * n)) * math.sqrt(2.0 / n)
    m[0] /= math.sqrt(2.0)
    return m


class PatchAutoencoder(nn.Module):
    """Fixed (parameter-free) patch codec: per colour channel, the lowest-frequency DCT coefficients
    of each (pt x ph x pw) space-time patch.

    With ``coefficients = pt*ph*pw`` it is lossless (an orthonormal change of basis); fewer keeps the
    smoothest part of every patch, like a VAE's compression but without learning. Coefficients are
    scaled by ``1/sqrt(pt*ph*pw)`` so the first channel of each colour is the patch mean in [-1, 1].

    Latent channels are ``3 * coefficients`` ordered colour-major.

    ``causal``: like Wan's 3D VAE, the first frame is a latent frame of its own and the rest go in
    groups of pt, so F = 1 + pt·n frames (121 -> 31 latent frames for pt = 4).
    """

    def __init__(self, patch: tuple[int, int, int] = (1, 8, 8), coefficients: int | None = None,
                 causal: bool = False):
        super().__init__()
        self.causal = bool(causal)
        pt, ph, pw = (int(p) for p in patch)
        if min(pt, ph, pw) < 1:
            raise ValueError(f"autoencoder patch {patch}: every size must be >= 1")
        n = pt * ph * pw
        coefficients = n if coefficients is None else int(coefficients)
        if not 1 <= coefficients <= n:
            raise ValueError(f"autoencoder coefficients={coefficients}: must be in [1, {n}] "
                             f"for patch {pt}x{ph}x{pw}")
        self.patch = (pt, ph, pw)
        self.coefficients = coefficients
        self.latent_channels = 3 * coefficients
        basis = torch.kron(torch.kron(_dct_matrix(pt), _dct_matrix(ph)), _dct_matrix(pw))  # (n, n)
        # Lowest total frequency first, so truncation keeps the smooth part of the patch.
        ft, fh, fw = torch.meshgrid(torch.arange(pt), torch.arange(ph), torch.arange(pw), indexing="ij")
        order = torch.argsort((ft + fh + fw).flatten() * n + torch.arange(n), stable=True)
        self.register_buffer("basis", basis[order[:coefficients]].float(), persistent=False)  # (k, n)
        self.scale = 1.0 / math.sqrt(n)

    def latent_shape(self, frames: int, height: int, width: int) -> tuple[int, int, int, int]:
        pt, ph, pw = self.patch
        padded = frames + (pt - 1 if self.causal else 0)
        if padded % pt or height % ph or width % pw:
            kind = "1 + a multiple of" if self.causal else "a multiple of"
            raise ValueError(f"video {frames}x{height}x{width} (frames x height x width) does not divide "
                             f"into {pt}x{ph}x{pw} patches (frames must be {kind} {pt}); change "
                             f"data.num_frames / data.height / data.width or autoencoder.patch")
        return padded // pt, self.latent_channels, height // ph, width // pw

    def frame_groups(self, frames: int) -> list[int]:
        return list(range(0, frames, self.patch[0]))

    def encode(self, video: torch.Tensor) -> torch.Tensor:
        """video (B, F, 3, H, W) -> latents (B, F/pt, 3k, H/ph, W/pw)."""
        b, F, C, H, W = video.shape
        f, _, h, w = self.latent_shape(F, H, W)
        pt, ph, pw = self.patch
        if self.causal and pt > 1:  # the first frame fills a group of its own
            video = torch.cat([video[:, :1].expand(b, pt - 1, C, H, W), video], dim=1)
        x = video.reshape(b, f, pt, C, h, ph, w, pw).permute(0, 1, 3, 4, 6, 2, 5, 7)
        x = x.reshape(b, f, C, h, w, pt * ph * pw)
        z = torch.einsum("bfchwn,kn->bfckhw", x, self.basis.to(x.dtype)) * self.scale
        return z.reshape(b, f, C * self.coefficients, h, w)

    def decode(self, latents: torch.Tensor) -> torch.Tensor:
        """latents (B, f, 3k, h, w) -> video (B, f*pt, 3, h*ph, w*pw) ((f-1)*pt + 1 frames if causal)."""
        b, f, c, h, w = latents.shape
        if c != self.latent_channels:
            raise ValueError(f"latents have {c} channels; this autoencoder makes {self.latent_channels}")
        pt, ph, pw = self.patch
        z = latents.reshape(b, f, 3, self.coefficients, h, w) / self.scale
        x = torch.einsum("bfckhw,kn->bfchwn", z, self.basis.to(z.dtype))
        x = x.reshape(b, f, 3, h, w, pt, ph, pw).permute(0, 1, 5, 2, 3, 6, 4, 7)
        x = x.reshape(b, f * pt, 3, h * ph, w * pw)
        return x[:, pt - 1:] if self.causal else x


def make_autoencoder(config: Mapping[str, Any]) -> VideoEncoder:
    """Build the autoencoder a training config names.

    ``kind: patch`` -> :class:`PatchAutoencoder` (``patch``, ``coefficients``, ``causal``);
    ``kind: "pkg.module:Factory"`` -> ``Factory(**options)``, which must satisfy :class:`VideoEncoder`.
    """
    kind = config.get("kind", "patch")
    if kind == "patch":
        return PatchAutoencoder(tuple(config.get("patch", (1, 8, 8))), config.get("coefficients"),
                                bool(config.get("causal", False)))
    module_name, _, attr = str(kind).partition(":")
    if not attr:
        raise ValueError(f"autoencoder.kind={kind!r}: use 'patch' or 'package.module:Factory'")
    factory = getattr(importlib.import_module(module_name), attr)
    encoder = factory(**dict(config.get("options") or {}))
    if not isinstance(encoder, VideoEncoder):
        raise TypeError(f"autoencoder {kind} does not implement encode/decode/latent_shape/frame_groups")
    return encoder
