"""The feature metrics' common interface: the weights check (:func:`check_weights`, from
:mod:`paradrive.scoring.networks`) that refuses a missing or wrong weights file before any video
is read, the extractor every network module provides and :func:`load_extractor`, and the metric
values computed from cached features (pure functions).

Metrics and their networks (one module each; docs/evaluation-features.md says how each is computed):

- ``fid``: Fréchet Inception Distance, :mod:`paradrive.scoring.inception` (pytorch-fid's
  Inception-v3 that matches the TF FID graph), 2048-d pool features of every frame;
- ``fvd``: Fréchet Video Distance, :mod:`paradrive.scoring.i3d` (Kinetics-400 I3D), 400-d logits
  of one 16-frame clip per video;
- ``clip_v``: frame-wise CLIP similarity, :mod:`paradrive.scoring.clipv` (a CLIPModel folder);
- ``iq``: VBench's imaging quality, :mod:`paradrive.scoring.musiq` (MUSIQ), per-frame scores.

Nothing here downloads: every weights file or folder is a path the user gives.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Protocol

import numpy as np

from paradrive.scoring.frechet import frechet_distance
from paradrive.scoring.networks import (FEATURE_METRICS, PUBLISHED_AT, Weights, as_frames, check_weights,
                                        load_state_dict, weights_sha256)

if TYPE_CHECKING:
    import torch

__all__ = ["FEATURE_METRICS", "PUBLISHED_AT", "Weights", "Extractor", "check_weights", "load_extractor",
           "fid", "fvd", "clip_v", "iq", "weights_sha256", "load_state_dict", "as_frames"]


class Extractor(Protocol):
    """One network, loaded on its device, turning one video's frames into that metric's features."""
    metric: str
    weights_sha256: str     # identifies the weights (cache key)

    def features(self, frames: np.ndarray) -> np.ndarray:
        """frames: (T, H, W, 3) uint8 RGB of one video -> this video's features as float64:
        fid: (T, 2048) per frame; fvd: (1, 400) per video; clip_v: (T, D) L2-normalised image
        embeddings; iq: (T,) per-frame quality scores (0-100)."""
        ...


def _loaders() -> dict[str, Callable[[Weights, torch.device], Extractor]]:
    from paradrive.scoring import clipv, i3d, inception, musiq

    return {"fid": inception.InceptionFeatures, "fvd": i3d.I3DFeatures,
            "clip_v": clipv.ClipFeatures, "iq": musiq.MusiqScores}


def load_extractor(weights: Weights, *, device: str) -> Extractor:
    """The network of ``weights.metric`` with its weights loaded, in eval mode on ``device``
    (``auto``: CUDA when present, else the CPU)."""
    from paradrive.devices import resolve_device

    return _loaders()[weights.metric](weights, resolve_device(device))


# --- metric values from cached features (pure functions) -------------------------------------

def _stacked(videos: list[np.ndarray], what: str) -> np.ndarray:
    rows = [np.asarray(v, dtype=np.float64).reshape(-1, np.shape(v)[-1]) for v in videos if np.size(v)]
    if not rows:
        raise ValueError(f"{what}: no features")
    return np.concatenate(rows, axis=0)


def fid(source: list[np.ndarray], generated: list[np.ndarray]) -> float:
    """FID between the frames of the source videos and those of the generated videos.

    source, generated: per video (T_i, 2048) Inception features; frames are pooled over the
    videos of each side (each frame one sample, as pytorch-fid pools images)."""
    return frechet_distance(_stacked(source, "fid source"), _stacked(generated, "fid generated"))


def fvd(source: list[np.ndarray], generated: list[np.ndarray]) -> float:
    """FVD between the source and the generated videos.

    source, generated: per video (1, 400) I3D logits (rows of several clips are pooled the same way)."""
    return frechet_distance(_stacked(source, "fvd source"), _stacked(generated, "fvd generated"))


def clip_v(source: np.ndarray, generated: np.ndarray) -> float:
    """CLIP-V of one video pair: the mean cosine similarity of matching frames, in [-1, 1]
    (the paper prints it x100).

    source, generated: (T, D) L2-normalised CLIP image embeddings of the same T frame indices."""
    a, b = np.asarray(source, dtype=np.float64), np.asarray(generated, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 2 or len(a) == 0:
        raise ValueError(f"clip_v: source {a.shape} and generated {b.shape} must be the same (T, D), T >= 1")
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    return float(np.mean(np.sum(a * b, axis=1)))


def iq(generated: np.ndarray) -> float:
    """IQ of one video: the mean of its per-frame MUSIQ scores (0-100, as the paper prints it).

    generated: (T,) per-frame scores."""
    scores = np.asarray(generated, dtype=np.float64).reshape(-1)
    if scores.size == 0:
        raise ValueError("iq: no frame scores")
    return float(scores.mean())
