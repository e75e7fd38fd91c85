"""Temporal consistency (TCE): the forward-backward end-point error of the flow between
consecutive frames, WorldScore's centre crop, OpenCV's DIS flow."""

from __future__ import annotations

import numpy as np
import pytest

from paradrive.scoring.flow import FlowSettings, dis_flow, forward_backward_error, tce

SHIFT = (3, -2)   # pixels a frame: right and up


def _texture(h: int = 120, w: int = 200, seed: int = 0) -> np.ndarray:
    """A smooth random RGB texture (noise blurred), wider than any frame cut from it."""
    import cv2

    noise = np.random.default_rng(seed).uniform(0, 255, (h, w, 3)).astype(np.float32)
    return np.clip(cv2.GaussianBlur(noise, (0, 0), 2.0) * 3.0 - 255.0, 0, 255).astype(np.uint8)


def _panning(frames: int = 6) -> np.ndarray:
    """A camera panning over the texture: frame t is the texture moved by t · SHIFT."""
    tex = _texture()
    dx, dy = SHIFT
    return np.stack([np.roll(tex, (t * dy, t * dx), axis=(0, 1))[20:116, 30:190]
                     for t in range(frames)])


def test_the_flow_of_a_known_shift_is_that_shift():
    video = _panning()
    flow = dis_flow(video[0], video[1])
    centre = flow[20:-20, 20:-20].reshape(-1, 2)
    epe = np.linalg.norm(centre - np.array(SHIFT, dtype=np.float32), axis=1)
    assert np.median(epe) < 0.1 and epe.mean() < 0.3


def test_a_consistent_video_has_a_small_tce_and_noise_a_large_one():
    steady = tce(_panning())
    assert steady.shape == (5,) and steady.mean() < 0.2
    rng = np.random.default_rng(1)
    flicker = rng.integers(0, 256, (6, 96, 160, 3), dtype=np.uint8)
    assert tce(flicker).mean() > 5 * steady.mean() + 0.5


def test_the_error_of_exact_flows_is_zero_and_of_a_one_way_flow_its_length():
    h, w = 60, 80
    fwd = np.broadcast_to(np.array([2.0, 1.0], dtype=np.float32), (h, w, 2))
    assert forward_backward_error(fwd, -fwd) == pytest.approx(0.0, abs=1e-9)
    # no motion back: every point ends where the forward flow took it, sqrt(5) px away
    assert forward_backward_error(fwd, np.zeros_like(fwd)) == pytest.approx(np.sqrt(5.0))


def test_only_the_centre_crop_counts():
    h, w = 60, 80
    fwd = np.zeros((h, w, 2), dtype=np.float32)
    fwd[:15], fwd[-15:], fwd[:, :15], fwd[:, -15:] = 50.0, 50.0, 50.0, 50.0   # the borders
    assert forward_backward_error(fwd, np.zeros_like(fwd), crop_px=30) == pytest.approx(0.0)
    assert forward_backward_error(fwd, np.zeros_like(fwd), crop_px=0) > 10.0


def test_a_frame_smaller_than_the_crop_or_a_one_frame_video_is_refused():
    with pytest.raises(ValueError, match="smaller than the 30-pixel TCE crop"):
        forward_backward_error(np.zeros((20, 40, 2)), np.zeros((20, 40, 2)))
    with pytest.raises(ValueError, match="two frames or more"):
        tce(_panning(1), FlowSettings())
