"""Frames as they come: a variable-frame-rate file is read by its timestamps, repeated frames
(a clip resampled to a higher rate) are dropped and recorded with the clock that remains, and
the synthetic street comes out at the same scale from its clean, variable-rate and duplicated
encodes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import FREEWAY, FREEWAY_VIDEO

from paradrive.ingest.export import export_scene
from paradrive.ingest.frameclock import (Clock, frame_changes, frames_at, is_variable, read_clock,
                                         repeated_frames)
from paradrive.ingest.sfm import path_length
from paradrive.scene import load_scene
from paradrive.stages.ingest import ingest, params_of
from paradrive.synthetic import SyntheticStreet
from paradrive.uri import parse_uri
from paradrive.video import decode_frames, encode_video

STREET = "synthetic:demo?seed=7&frames=24&width=320&height=192"
RATIO = params_of().video_repeat_ratio   # the stage file's default
H, W = 90, 160


# --------------------------------------------------------------------------- the detector

def _scene_at(shift: np.ndarray) -> np.ndarray:
    """A smooth textured picture (H, W) float, moved ``shift`` pixels to the left (any real)."""
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    x = xx + shift
    return (128 + 40 * np.sin(x / 3.1 + yy / 7.0) + 30 * np.sin(x / 5.3 - yy / 2.9)
            + 20 * np.sin(x / 1.7 + 1.0))


def _noisy(picture: np.ndarray, rng: np.random.Generator, sigma: float = 1.0) -> np.ndarray:
    """uint8 (H, W, 3) of a grey picture with a camera's noise."""
    grey = picture + rng.normal(0, sigma, picture.shape)
    return np.repeat(np.clip(np.round(grey), 0, 255).astype(np.uint8)[..., None], 3, axis=2)


def _drive(speeds_px: np.ndarray, seed: int = 0, traffic: bool = False) -> list[np.ndarray]:
    """Frames of a camera moving ``speeds_px[i]`` pixels between frame i and i + 1; with
    ``traffic`` the picture stands still and a car-sized block crosses it at 4 px a frame."""
    rng = np.random.default_rng(seed)
    offsets = np.concatenate([[0.0], np.cumsum(speeds_px)])
    frames = []
    for i, offset in enumerate(offsets):
        picture = _scene_at(np.float64(offset))
        if traffic:
            x = int(10 + 4 * i) % (W - 30)
            picture[40:70, x:x + 30] = 230.0
        frames.append(_noisy(picture, rng))
    return frames


def _with_repeats(frames: list[np.ndarray], after: list[int], seed: int = 1) -> tuple[list[np.ndarray], list[int]]:
    """The frames with a near-copy (one grey level up or down at a tenth of the pixels, as a
    resampler's filter leaves it) inserted after each of ``after``; and where the copies landed."""
    rng = np.random.default_rng(seed)
    out, where = [], []
    for i, frame in enumerate(frames):
        out.append(frame)
        if i in after:
            jitter = rng.integers(-1, 2, frame.shape) * (rng.random(frame.shape) < 0.1)
            out.append(np.clip(frame.astype(np.int16) + jitter, 0, 255).astype(np.uint8))
            where.append(len(out) - 1)
    return out, where


def test_near_duplicates_among_moving_frames_are_found_and_nothing_else():
    frames = _drive(np.full(29, 3.0))
    with_copies, copies = _with_repeats(frames, [4, 5, 12, 20, 27])
    found = np.flatnonzero(repeated_frames(frame_changes(with_copies), RATIO))
    assert found.tolist() == copies
    assert not repeated_frames(frame_changes(frames), RATIO).any()


def test_slow_driving_braking_and_moving_off_are_not_repeats():
    """A car creeping at a tenth of a pixel a frame, one braking from 3 px a frame to a stop
    and standing, and one moving off again: every frame is kept, though the slowest change
    less than a tenth of the fastest."""
    creeping = frame_changes(_drive(np.full(40, 0.1)))
    braking = np.concatenate([np.linspace(3.0, 0.0, 30), np.zeros(10), np.linspace(0.0, 3.0, 30)])
    stop_and_go = frame_changes(_drive(braking, seed=2))
    assert np.nanmin(stop_and_go[1:]) < 0.1 * np.nanmax(stop_and_go[1:])
    assert not repeated_frames(creeping, RATIO).any() and not repeated_frames(stop_and_go, RATIO).any()


def test_a_stopped_car_with_traffic_passing_keeps_its_frames_and_loses_its_copies():
    standing = _drive(np.zeros(29), traffic=True)
    assert not repeated_frames(frame_changes(standing), RATIO).any()
    with_copies, copies = _with_repeats(standing, [3, 9, 10, 22])
    assert np.flatnonzero(repeated_frames(frame_changes(with_copies), RATIO)).tolist() == copies


def test_a_still_picture_is_not_repeats_of_itself():
    """A parked camera in an empty street: frames that differ only by noise, or not at all,
    cannot be told from repeats, and none is dropped (docs/scene-layout.md)."""
    noise_only = frame_changes(_drive(np.zeros(30)))
    frozen = frame_changes([_noisy(_scene_at(np.float64(0)), np.random.default_rng(0), 0)] * 12)
    assert not repeated_frames(noise_only, RATIO).any() and not repeated_frames(frozen, RATIO).any()


def test_variable_rate_is_told_from_a_constant_one():
    assert not is_variable(np.arange(50) / 25.0)
    # a constant 29.97 fps in a Matroska file's whole milliseconds: 33 and 34 ms intervals
    assert not is_variable(np.round(np.arange(50) * 1001 / 30000, 3))
    jittered = np.cumsum(np.r_[0, np.random.default_rng(0).uniform(0.030, 0.045, 49)])
    assert is_variable(jittered)
    gap = np.r_[np.arange(10), np.arange(11, 20)] / 10.0   # one frame lost
    assert is_variable(gap)


def test_frames_are_taken_by_time_from_the_kept_ones():
    times = np.r_[0.0, 0.1, 0.2, 0.26, 0.3, 0.4, 0.41, 0.5, 0.6, 0.7]
    clock = Clock(times, "timestamps", 25.0, np.zeros(10), repeated=(6,))
    assert clock.kept == [0, 1, 2, 3, 4, 5, 7, 8, 9] and clock.variable_rate
    assert clock.fps == pytest.approx(10.0)   # the median interval of what remains: 0.1 s
    assert frames_at(clock, 100.0, 0.0, None) == clock.kept
    assert frames_at(clock, 5.0, 0.0, None) == [0, 2, 5, 8]   # nearest to 0, 0.2, 0.4, 0.6 s
    assert frames_at(clock, 100.0, 0.12, 0.45) == [2, 3, 4, 5]
    doc = clock.doc()
    assert doc["repeated_frames_dropped"] == [6] and doc["variable_rate"] is True
    assert doc["fps"] == pytest.approx(10.0) and doc["interval_s"]["min"] == pytest.approx(0.01)


# --------------------------------------------------------------------------- files


def test_the_freeway_clip_has_a_constant_rate_and_no_repeats():
    """A real 1280x720 dashcam clip: 160 frames at 25 fps, none taken for a repeat."""
    if not FREEWAY_VIDEO.is_file():
        pytest.skip(f"the real freeway clip is not here ({FREEWAY})")
    clock = read_clock(FREEWAY_VIDEO, (160, 25.0, 1280, 720), scene_id="freeway", repeat_ratio=RATIO)
    assert clock.source == "timestamps" and len(clock.times) == 160
    assert not clock.variable_rate and clock.repeated == () and clock.fps == 25.0
    np.testing.assert_allclose(clock.times, np.arange(160) / 25.0, atol=1e-9)


# --------------------------------------------------------------------------- the street, three ways

@pytest.fixture(scope="module")
def street_encodes(tmp_path_factory) -> dict[str, tuple[str, np.ndarray]]:
    """The synthetic street's recorded video (24 frames at 10 fps) and two files of it as they
    come from the internet, each with its ``video:`` URI at the video's own rate and the times
    its frames show: ``vfr``, a variable-rate file that lost frames 5, 11 and 17 (0.1 and 0.2 s
    intervals); ``doubled``, resampled to 20 fps, every frame shown twice (the copy jittered by
    a grey level at a fifth of its pixels, as a resampler's filter leaves it)."""
    out = tmp_path_factory.mktemp("clock")
    uri = export_scene(STREET, "video", out, params_of())
    parsed = parse_uri(uri)
    query = "&".join(f"{k}={v}" for k, v in parsed.query.items() if k not in ("fps", "truth"))
    clean = decode_frames(parsed.path)
    times = np.arange(24) / 10.0
    lost = [i for i in range(24) if i not in (5, 11, 17)]
    encode_video(out / "vfr.mp4", clean[lost], 10.0, times=times[lost], crf=18)
    rng = np.random.default_rng(0)
    twice = []
    for frame in clean:
        jitter = rng.integers(-1, 2, frame.shape) * (rng.random(frame.shape) < 0.2)
        twice += [frame, np.clip(frame.astype(np.int16) + jitter, 0, 255).astype(np.uint8)]
    encode_video(out / "doubled.mp4", twice, 20.0, crf=18)
    return {"clean": (f"video:{parsed.path}?{query}", times),
            "vfr": (f"video:{out / 'vfr.mp4'}?{query}", times[lost]),
            "doubled": (f"video:{out / 'doubled.mp4'}?{query}", np.arange(48) / 20.0)}


@pytest.fixture(scope="module")
def street_scenes(tmp_path_factory, street_encodes) -> dict[str, tuple[dict, float]]:
    """Each encode ingested: its scene.json and its metric path length (m)."""
    root = tmp_path_factory.mktemp("clock-scenes")
    scenes = {}
    for name, (uri, _) in street_encodes.items():
        ingest(uri, root / name, params_of())
        doc = json.loads((root / name / "scene.json").read_text())
        scenes[name] = (doc, path_length(load_scene(root / name).c2w("front")))
    return scenes


def _frame_times(doc: dict) -> np.ndarray:
    return np.array([f["timestamp_us"] for f in doc["frames"]]) / 1e6


@pytest.mark.slow
def test_the_variable_rate_file_keeps_its_clock_and_the_scale(street_scenes, street_encodes):
    doc, length = street_scenes["vfr"]
    clean, clean_length = street_scenes["clean"]
    clock = doc["video"]["clock"]
    assert clock["variable_rate"] is True and clock["timestamps"] == "timestamps"
    assert clock["repeated_frames_dropped"] == [] and clock["frames"] == 21
    # every frame at the time the file shows it, to the microsecond: 0.5 s is frame 4, 0.6 s 6
    _, times = street_encodes["vfr"]
    kept = doc["video"]["kept"]
    np.testing.assert_allclose(_frame_times(doc), times[kept[0]:kept[1] + 1], atol=1e-6)
    _same_scale(doc, length, clean, clean_length)


@pytest.mark.slow
def test_repeated_frames_are_dropped_and_recorded_with_the_clock_that_remains(street_scenes):
    doc, length = street_scenes["doubled"]
    clean, clean_length = street_scenes["clean"]
    clock = doc["video"]["clock"]
    assert clock["repeated_frames_dropped"] == list(range(1, 48, 2))
    assert clock["header_fps"] == pytest.approx(20.0) and clock["fps"] == pytest.approx(10.0)
    assert doc["video"]["native_fps"] == pytest.approx(10.0)
    assert doc["video"]["source_frames"] == list(range(0, 48, 2))[slice(doc["video"]["kept"][0],
                                                                        doc["video"]["kept"][1] + 1)]
    np.testing.assert_allclose(np.diff(_frame_times(doc)), 0.1, atol=1e-6)
    assert doc["fps"] == pytest.approx(10.0)
    assert doc["video"]["registered"] == f"0-{len(doc['frames']) - 1}"


@pytest.mark.slow
def test_the_doubled_file_has_the_clean_scale(street_scenes):
    """The resampled file's road's motion lies 9 % from the clean encode's (the pixels of
    another encode, the poses alike); one more encode of each file's frames shows that
    sensitivity (its ``codec`` part), so both state it and agree within it."""
    doc, length = street_scenes["doubled"]
    clean, clean_length = street_scenes["clean"]
    for scene in (doc, clean):
        motion = scene["video"]["scale"]["road_motion"]
        assert motion["codec"] > motion["scatter"], motion
    _same_scale(doc, length, clean, clean_length)


@pytest.mark.slow
def test_the_clean_encode_drops_nothing(street_scenes):
    doc, _ = street_scenes["clean"]
    clock = doc["video"]["clock"]
    assert clock["variable_rate"] is False and clock["repeated_frames_dropped"] == []
    assert clock["fps"] == 10.0 and clock["repeat_detection"]["done"] is True
    np.testing.assert_allclose(_frame_times(doc), np.arange(24) / 10.0, atol=1e-6)


def _same_scale(doc: dict, length: float, clean: dict, clean_length: float) -> None:
    """Every frame registered, and the path (m) of the same drive (its first to its last frame)
    as long as the clean encode's within two of their combined stated uncertainties, and as
    the street's within two of its own (the goal test_ingest_video.py holds the clean one to:
    encodes of one clip scatter by a few per cent)."""
    mine, theirs = doc["video"]["scale"]["uncertainty"], clean["video"]["scale"]["uncertainty"]
    assert doc["video"]["registered"] == f"0-{len(doc['frames']) - 1}"
    assert abs(length / clean_length - 1) <= 2 * np.hypot(mine, theirs), (length, clean_length,
                                                                         mine, theirs)
    street = SyntheticStreet(name="demo", seed=7, frames=24, width=320, height=192)
    assert abs(length / path_length(street.c2w("front")) - 1) <= 2 * mine
