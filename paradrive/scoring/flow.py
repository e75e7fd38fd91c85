"""Temporal consistency error (TCE): the forward-backward end-point error of the optical flow
between consecutive frames of a generated video, in pixels (lower is better).

The paper (its supplement, "Temporal Consistency Error") follows WorldScore's photometric
consistency: for each pair of consecutive frames (I_t, I_t+1) the forward flow moves every point
x_t of a centre crop to x̂_t+1 = x_t + φ_f(x_t), the backward flow brings it back,
x'_t = x̂_t+1 + φ_b(x̂_t+1), and E(I_t, I_t+1) is the mean of |x'_t − x_t|; TCE is the mean of E
over the T − 1 pairs. As WorldScore computes it: every pixel of the centre crop that leaves
``crop_px`` / 2 pixels at each border (30 px in all, its default), the backward flow read at the
nearest pixel of x̂_t+1 clipped into the crop, frames at the video's own resolution.

The paper's flow is SEA-RAFT. Given ``--flow-weights``, the flow is RAFT's
(:mod:`paradrive.scoring.raft`); without, it is OpenCV's DIS (dense inverse search, its
``MEDIUM`` preset, on the grey frames), which needs no weights: a substitute, whose errors are not
SEA-RAFT's, so its TCE compares models scored the same way, not a number of the paper's table.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["FLOW_METHOD", "FlowSettings", "dis_flow", "forward_backward_error", "tce"]

FLOW_METHOD = "opencv-dis-medium"

# (a, b): uint8 (H, W, 3) RGB frames -> float32 (H, W, 2) flow from a to b, pixels (dx, dy)
Flow = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class FlowSettings:
    """How TCE is measured: WorldScore's 30-pixel crop (15 a side) and the flow that runs
    (``weights``: a RAFT weights file, :mod:`paradrive.scoring.raft`; None: DIS)."""

    crop_px: int = 30
    method: str = FLOW_METHOD
    weights: Path | None = None

    def key(self) -> dict:
        return {"crop_px": self.crop_px, "method": self.method}


def dis_flow(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """OpenCV's DIS optical flow from ``a`` to ``b`` (uint8 (H, W, 3) RGB): (H, W, 2) float32."""
    import cv2

    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)  # type: ignore[attr-defined]
    grey_a = cv2.cvtColor(np.ascontiguousarray(a), cv2.COLOR_RGB2GRAY)
    grey_b = cv2.cvtColor(np.ascontiguousarray(b), cv2.COLOR_RGB2GRAY)
    return dis.calc(grey_a, grey_b, None).astype(np.float32)


def forward_backward_error(forward: np.ndarray, backward: np.ndarray, crop_px: int = 30) -> float:
    """E(I_t, I_t+1): the mean distance, pixels, between each point of the centre crop and where
    the forward flow then the backward flow (read at the nearest pixel, clipped into the crop)
    bring it. forward, backward: (H, W, 2) flows t -> t+1 and t+1 -> t."""
    h, w = forward.shape[:2]
    ch, cw = h - crop_px, w - crop_px
    if ch < 1 or cw < 1:
        raise ValueError(f"a {w}x{h} frame is smaller than the {crop_px}-pixel TCE crop")
    y0, x0 = (h - ch) // 2, (w - cw) // 2
    fwd = forward[y0:y0 + ch, x0:x0 + cw].astype(np.float64)
    bwd = backward[y0:y0 + ch, x0:x0 + cw].astype(np.float64)
    y, x = np.meshgrid(np.arange(ch, dtype=np.float64), np.arange(cw, dtype=np.float64),
                       indexing="ij")
    xs, ys = x + fwd[..., 0], y + fwd[..., 1]
    xi = np.clip(np.rint(xs).astype(np.int64), 0, cw - 1)
    yi = np.clip(np.rint(ys).astype(np.int64), 0, ch - 1)
    back = bwd[yi, xi]
    return float(np.hypot(xs + back[..., 0] - x, ys + back[..., 1] - y).mean())


def tce(frames: np.ndarray, settings: FlowSettings = FlowSettings(),
        flow: Flow = dis_flow) -> np.ndarray:
    """The per-pair errors E(I_t, I_t+1), (T - 1,) pixels, of a video's uint8 (T, H, W, 3)
    frames; TCE is their mean."""
    if len(frames) < 2:
        raise ValueError(f"TCE needs two frames or more, the video has {len(frames)}")
    return np.array([forward_backward_error(flow(a, b), flow(b, a), settings.crop_px)
                     for a, b in zip(frames[:-1], frames[1:])], dtype=np.float64)
