"""Video helpers: real FFmpeg (PyAV) encode and decode, H.264 and lossless FFV1."""

from __future__ import annotations

import numpy as np
import pytest

from video_probe import probe_video

from paradrive.video import container_suffix, decode_frames, each_frame, encode_video, frame_times


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


ENCODE_ONE = """
import sys, numpy as np
from paradrive.video import encode_video
rng = np.random.default_rng(0)
base = rng.integers(0, 255, (232, 360, 3), dtype=np.uint8)
frames = [np.ascontiguousarray(base[i:i + 192, i:i + 320]) for i in range(20)]
print(encode_video(sys.argv[1], frames, 10.0, threads=1)["sha256"])
"""


def test_the_bytes_do_not_depend_on_what_the_heap_held(tmp_path):
    """The same frames give the same bytes whatever the process's memory held before: glibc fills
    freed and new blocks with another byte under each MALLOC_PERTURB_ (on a CPU with AVX-512,
    x264's own AVX-512 functions gave another file under 85 than under 0 and 170)."""
    import os
    import subprocess
    import sys

    digests = set()
    for k, perturb in enumerate(("0", "85", "170")):
        env = {**os.environ, "MALLOC_PERTURB_": perturb}
        done = subprocess.run([sys.executable, "-c", ENCODE_ONE, str(tmp_path / f"{k}.mp4")],
                              env=env, capture_output=True, text=True, check=True)
        digests.add(done.stdout.split()[-1])
    assert len(digests) == 1, digests


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


def _textured(n: int, h: int, w: int) -> list[np.ndarray]:
    """Noise on a gradient: sharp edges in every colour, where conversions and filters differ."""
    rng = np.random.default_rng(3)
    return [np.clip(f.astype(np.int16) + rng.integers(-60, 60, f.shape), 0, 255).astype(np.uint8)
            for f in _frames(n, h, w)]


def _direct_pyav(path, **reformat) -> np.ndarray:
    """Every frame converted by PyAV itself, each ``VideoFrame`` with its own conversion (R, G, B
    last; planar formats as PyAV orders them)."""
    import av

    with av.open(str(path)) as container:
        return np.stack([f.reformat(**reformat).to_ndarray() for f in container.decode(video=0)])


@pytest.mark.parametrize("threads", [1, 0])
def test_frames_are_bit_identical_to_a_direct_pyav_decode(tmp_path, threads):
    path = tmp_path / "t.mp4"
    encode_video(path, _textured(6, 48, 64), 10.0, preset="ultrafast")
    area = {"width": 40, "height": 30, "interpolation": "AREA"}
    for size, reformat in ((None, {}), ((30, 40), area)):
        rgb = _direct_pyav(path, format="rgb24", **reformat)
        np.testing.assert_array_equal(decode_frames(path, size=size, threads=threads), rgb)
        planar: dict[int, np.ndarray] = {}
        each_frame(path, None, lambda i, planes: planar.setdefault(i, np.stack(planes)), size=size,
                   threads=threads, planar=True)
        gbrp = _direct_pyav(path, format="gbrp", **reformat)   # to_ndarray gives it as (H, W, RGB)
        np.testing.assert_array_equal(np.stack([planar[i] for i in range(6)]), gbrp.transpose(0, 3, 1, 2))


def test_a_pass_converts_every_frame_through_one_swscale_context(tmp_path):
    """Setting up a conversion costs as much as converting a small frame: a pass over a video
    must not give each frame its own (``VideoFrame.reformat`` / ``to_ndarray(format=...)`` do)."""
    import sys
    from collections import Counter

    path = tmp_path / "t.mp4"
    encode_video(path, _textured(7, 48, 64), 10.0, preset="ultrafast")
    calls: Counter = Counter()
    contexts: set[int] = set()

    def profile(frame, event, arg) -> None:
        if event == "c_call":
            calls[getattr(arg, "__qualname__", "")] += 1
            if getattr(arg, "__qualname__", "") == "VideoReformatter.reformat":
                contexts.add(id(arg.__self__))

    for planar, size in ((True, None), (False, (24, 32))):
        calls.clear()
        contexts.clear()
        sys.setprofile(profile)
        try:
            each_frame(path, [1, 2, 3, 5], lambda i, pixels: None, planar=planar, size=size)
        finally:
            sys.setprofile(None)
        assert calls["VideoReformatter.reformat"] == 4 and len(contexts) == 1
        assert calls["VideoFrame.reformat"] == 0


def test_a_variable_rate_file_is_decoded_by_its_timestamps(tmp_path):
    """Frames [4, 10, 16, 20, 23] of a VFR file, sought and decoded from the start, are the
    frames written there, and frame_times gives when each is shown."""
    times = np.cumsum(np.r_[0.0, np.tile([0.04, 0.06, 0.033, 0.067], 6)[:23]])
    frames = [np.full((48, 64, 3), 10 * i, np.uint8) for i in range(24)]
    for name in ("vfr.mp4", "vfr.mkv"):
        path = tmp_path / name
        encode_video(path, frames, 25.0, times=times, preset="ultrafast", gop=6,
                     codec="libx264" if name.endswith("mp4") else "ffv1")
        got, _ = frame_times(path)
        np.testing.assert_allclose(got, times, atol=5e-4)   # Matroska keeps milliseconds
        picks = [4, 10, 16, 20, 23]
        for seek in (True, False):
            decoded = decode_frames(path, picks, seek=seek)
            np.testing.assert_allclose(decoded[:, 0, 0, 0], 10 * np.asarray(picks), atol=3)
        assert len(decode_frames(path)) == 24
        stats: dict = {}   # a seek by timestamp starts at the keyframe before frame 20 (18)
        np.testing.assert_allclose(decode_frames(path, [20], stats=stats)[:, 0, 0, 0], 200, atol=3)
        assert stats["decoded"] < 12


def test_a_constant_rate_file_is_timed_by_its_frame_numbers(tmp_path):
    encode_video(tmp_path / "c.mp4", _frames(9), 29.97, preset="ultrafast")
    times, rate = frame_times(tmp_path / "c.mp4")
    np.testing.assert_allclose(times, np.arange(9) * 1001 / 30000, atol=1e-4)
    assert rate == pytest.approx(29.97, rel=1e-3)
