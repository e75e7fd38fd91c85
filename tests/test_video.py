"""Video helpers: real FFmpeg (PyAV) encode and decode, H.264 and lossless FFV1."""

from __future__ import annotations

import numpy as np
import pytest

from video_probe import probe_video

from paradrive.video import container_suffix, decode_frames, each_frame, encode_video


def _frames(n: int = 9, h: int = 48, w: int = 64) -> list[np.ndarray]:
    """Smooth gradients whose brightness encodes the frame number (order is checkable)."""
    yy, xx = np.mgrid[0:h, 0:w]
    out = []
    for i in range(n):
        img = np.stack([xx * 2, yy * 3, np.full_like(xx, 20 * i)], -1)
        out.append(np.clip(img, 0, 255).astype(np.uint8))
    return out


def test_h264_round_trip_keeps_frame_count_order_and_size(tmp_path):
    frames = _frames()
    info = encode_video(tmp_path / "a.mp4", frames, 10.0, crf=18, preset="ultrafast")
    decoded = decode_frames(tmp_path / "a.mp4")
    assert info["frames"] == 9 and decoded.shape == (9, 48, 64, 3)
    # the blue channel carries 20 * frame index: decoded order matches
    blue = decoded[..., 2].reshape(9, -1).mean(1)
    assert np.allclose(blue, 20 * np.arange(9), atol=3)
    assert np.abs(decoded.astype(int) - np.stack(frames)).mean() < 3
    probe = probe_video(tmp_path / "a.mp4")
    assert probe["codec"] == "h264" and probe["pix_fmt"] == "yuv420p"
    assert probe["frames"] == 9 and probe["fps"] == pytest.approx(10.0)


def test_ffv1_is_lossless_in_mkv(tmp_path):
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 256, (30, 41, 3), dtype=np.uint8) for _ in range(5)]
    assert container_suffix("ffv1") == ".mkv"
    encode_video(tmp_path / "a.mkv", frames, 12.5, codec="ffv1")
    assert np.array_equal(decode_frames(tmp_path / "a.mkv"), np.stack(frames))
    assert probe_video(tmp_path / "a.mkv")["codec"] == "ffv1"


def test_encoding_is_deterministic_and_checksummed(tmp_path):
    from paradrive.io import sha256_file

    a = encode_video(tmp_path / "a.mp4", _frames(), 10.0, preset="ultrafast")
    b = encode_video(tmp_path / "b.mp4", _frames(), 10.0, preset="ultrafast")
    assert a["sha256"] == b["sha256"] == sha256_file(tmp_path / "a.mp4")
    assert a["bytes"] == (tmp_path / "a.mp4").stat().st_size


def test_odd_size_h264_is_refused_and_leaves_no_file(tmp_path):
    frames = [np.zeros((31, 40, 3), np.uint8)] * 3
    with pytest.raises(ValueError, match="even"):
        encode_video(tmp_path / "odd.mp4", frames, 10.0)
    assert list(tmp_path.iterdir()) == []


def test_wrong_container_mixed_sizes_and_empty_input_are_errors(tmp_path):
    with pytest.raises(ValueError, match=".mkv"):
        encode_video(tmp_path / "a.mp4", _frames(2), 10.0, codec="ffv1")
    with pytest.raises(ValueError, match="frame 1"):
        encode_video(tmp_path / "b.mp4", [_frames(1)[0], np.zeros((8, 8, 3), np.uint8)], 10.0)
    with pytest.raises(ValueError, match="no frames"):
        encode_video(tmp_path / "c.mp4", [], 10.0)
    assert list(tmp_path.iterdir()) == []


def test_each_frame_hands_over_every_frame_once_in_order(tmp_path):
    encode_video(tmp_path / "a.mkv", _frames(4), 10.0, codec="ffv1")
    seen = []
    each_frame(tmp_path / "a.mkv", None, lambda i, rgb: seen.append((i, rgb.shape)))
    assert seen == [(i, (48, 64, 3)) for i in range(4)]


def test_gop_sets_the_keyframe_interval(tmp_path):
    import av

    frames = _frames(40, 32, 48)
    path = tmp_path / "g.mp4"
    encode_video(path, frames, fps=10.0, gop=10, preset="ultrafast")
    with av.open(str(path)) as container:
        keys = [i for i, packet in enumerate(
            sorted((p for p in container.demux(video=0) if p.size), key=lambda p: p.pts))
            if packet.is_keyframe]
    assert keys == [0, 10, 20, 30]
