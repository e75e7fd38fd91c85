"""Video files with PyAV (FFmpeg): encode uint8 RGB frames, decode them back, probe a file.

Two codecs are supported:

* ``libx264`` (H.264, ``yuv420p`` by default) in an ``.mp4`` container: small and plays everywhere;
* ``ffv1`` (lossless, ``bgr0`` so RGB survives exactly) in an ``.mkv`` container.

Frames are stamped with ``pts = i`` in a ``1/fps`` time base, so decoding yields them in order
with no frame dropped or duplicated. Every file is written under a temporary name and renamed.

Frames are read by their timestamps: frame ``i`` is the ``i``-th frame the file presents (its
``i``-th smallest timestamp), whatever its rate, so a variable-frame-rate file (a phone's, or
one cut and joined) decodes as readily as a constant-rate one, and :func:`frame_times` gives
when each is shown. A seek goes to the timestamp of the first wanted frame, read from the
file's packets (demuxed, not decoded: a few milliseconds for a 200-frame 720p clip).

The same frames and settings give the same bytes at a given encoder thread count: on a CPU with
AVX-512, x264's AVX-512 functions made the output depend on what the process's heap held before
(the same frames encoded after other work, or under ``MALLOC_PERTURB_``, came out different), so
x264 is held to its AVX2 functions there: a different encode from the AVX-512 functions', and a
repeatable one.
"""

from __future__ import annotations

import functools
import os
import re
from collections.abc import Callable, Iterable, Sequence
from fractions import Fraction
from typing import Any
from pathlib import Path

import numpy as np

from paradrive.errors import ParaDriveError
from paradrive.io import atomic_path, sha256_file

__all__ = ["CODECS", "container_suffix", "encode_video", "decode_frames", "each_frame",
           "frame_times"]

# B-frames are reordered over at most 16 frames in H.264 and HEVC: packets read this far past a
# frame fix its place among the presented frames
REORDER_MARGIN = 64

# codec -> (container suffix, FFmpeg container format, default pixel format)
CODECS = {
    "libx264": (".mp4", "mp4", "yuv420p"),
    "ffv1": (".mkv", "matroska", "bgr0"),
}


def container_suffix(codec: str) -> str:
    """File suffix for ``codec``: ``.mp4`` for H.264, ``.mkv`` for FFV1."""
    if codec not in CODECS:
        raise ValueError(f"unknown codec {codec!r}; use one of {', '.join(CODECS)}")
    return CODECS[codec][0]


@functools.cache
def x264_params() -> dict[str, str]:
    """libx264's extra options on this CPU: ``asm=AVX2`` where the CPU has AVX-512 (see the
    module's docstring), none elsewhere."""
    try:
        cpu = Path("/proc/cpuinfo").read_text(encoding="utf-8", errors="replace")
    except OSError:
        return {}
    return {"x264-params": "asm=AVX2"} if re.search(r"\bavx512f\b", cpu) else {}


def _rate(fps: float) -> Fraction:
    if not (fps > 0 and np.isfinite(fps)):
        raise ValueError(f"fps must be positive, got {fps}")
    # 29.97 -> 30000/1001; integer rates stay exact.
    return Fraction(fps).limit_denominator(1001)


def encode_video(path: str | os.PathLike, frames: Iterable[np.ndarray], fps: float, *,
                 codec: str = "libx264", crf: int = 18, preset: str = "medium",
                 pix_fmt: str | None = None, threads: int = 0, gop: int | None = None,
                 times: Sequence[float] | None = None) -> dict:
    """Encode uint8 RGB frames (H, W, 3), all the same size, into ``path``.

    times: when each frame is shown (seconds, increasing; one per frame) for a variable-rate
    file, stamped in a 1/90000 s time base with ``fps`` as the stream's nominal rate; None =
    frame ``i`` at ``i / fps``.

    codec: ``libx264`` (``crf``, ``preset``, ``pix_fmt`` default ``yuv420p``, whose 2x2 chroma
    needs even width and height) or ``ffv1`` (lossless; ``crf`` and ``preset`` are ignored).
    ``threads``: encoder threads (0 = FFmpeg's choice). ``gop``: frames between keyframes
    (None = the encoder's default); short GOPs let readers seek into a clip cheaply. The container follows the codec, so
    ``path`` must end in :func:`container_suffix`. Returns ``{"frames", "width", "height",
    "bytes", "sha256"}`` of the written file.
    """
    import av

    path = Path(path)
    suffix, fmt, default_pix = CODECS.get(codec, (None, None, None))
    if suffix is None:
        raise ValueError(f"unknown codec {codec!r}; use one of {', '.join(CODECS)}")
    if path.suffix != suffix:
        raise ValueError(f"{path}: a {codec} stream goes in a '{suffix}' file")
    pix_fmt = str(pix_fmt or default_pix)
    rate = _rate(fps)
    base = Fraction(1) / rate if times is None else Fraction(1, 90000)
    stamps = None if times is None else _stamps(path, times)
    count, size = 0, (0, 0)
    with atomic_path(path) as tmp:
        with av.open(str(tmp), mode="w", format=fmt) as container:
            stream: Any = None
            for frame in frames:
                frame = np.ascontiguousarray(frame)
                if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
                    raise ValueError(f"{path}: frames must be uint8 (H, W, 3), got "
                                     f"{frame.dtype} {frame.shape}")
                if stream is None:
                    size = frame.shape[:2]
                    h, w = size
                    if pix_fmt.startswith("yuv420") and (w % 2 or h % 2):
                        raise ValueError(f"{path}: {pix_fmt} needs even width and height, got "
                                         f"{w}x{h}; choose an even output size")
                    stream = container.add_stream(codec, rate=rate)
                    if stamps is not None:
                        stream.time_base = stream.codec_context.time_base = base
                    stream.width, stream.height = w, h
                    stream.pix_fmt = pix_fmt
                    stream.thread_count = int(threads)
                    _set_options(stream, codec, crf, preset, gop)
                elif frame.shape[:2] != size:
                    raise ValueError(f"{path}: frame {count} is {frame.shape[1]}x{frame.shape[0]}, "
                                     f"the first was {size[1]}x{size[0]}")
                if stamps is not None and count >= len(stamps):
                    raise ValueError(f"{path}: more frames than the {len(stamps)} times given")
                vf = av.VideoFrame.from_ndarray(frame, format="rgb24")
                vf.pts = count if stamps is None else stamps[count]
                vf.time_base = base
                for packet in stream.encode(vf):
                    container.mux(packet)
                count += 1
            if stream is None:
                raise ValueError(f"{path}: no frames to encode")
            if stamps is not None and count != len(stamps):
                raise ValueError(f"{path}: {len(stamps)} times given for {count} frames")
            for packet in stream.encode(None):
                container.mux(packet)
    return {"frames": count, "width": int(size[1]), "height": int(size[0]),
            "bytes": path.stat().st_size, "sha256": sha256_file(path)}


def _stamps(path: Path, times: Sequence[float]) -> list[int]:
    """``times`` (s) in a 1/90000 s time base; ValueError where they do not increase."""
    stamps = [int(round(float(t) * 90000)) for t in times]
    if any(b <= a for a, b in zip(stamps, stamps[1:])):
        raise ValueError(f"{path}: times must increase by at least 1/90000 s, got "
                         f"{list(times)[:8]}...")
    return stamps


def _set_options(stream: Any, codec: str, crf: int, preset: str, gop: int | None) -> None:
    """The encoder's options: x264's quality, speed and keyframes, or FFV1's checksums."""
    if gop:
        stream.codec_context.gop_size = int(gop)
    if codec == "libx264":
        stream.options = {"crf": str(int(crf)), "preset": str(preset), **x264_params()}
        if gop:
            stream.options = {**stream.options, "keyint_min": str(int(gop))}
    else:
        stream.options = {"level": "3", "slicecrc": "1"}


# --------------------------------------------------------------------------- decoding

def _presented(container, stream, upto: int | None = None) -> list[int] | None:
    """The timestamps (``stream.time_base`` units) of the frames ``stream`` presents, sorted: entry
    ``i`` is frame ``i``'s. Read from the packets (no decoding), all of them or up to ``upto``
    frames plus the reordering margin. Packets the container marks to discard (an edit list's
    lead-in) present nothing; None where a packet carries no timestamp."""
    stamps: list[int] = []
    for packet in container.demux(stream):
        if not packet.size or packet.is_discard:
            continue
        stamp = packet.pts if packet.pts is not None else packet.dts
        if stamp is None:
            return None
        stamps.append(int(stamp))
        if upto is not None and len(stamps) > upto + REORDER_MARGIN:
            break
    return sorted(stamps)


def frame_times(path: str | Path) -> tuple[np.ndarray, float] | None:
    """When each frame of ``path`` is presented: (F,) float64 seconds from the first frame, in
    frame order (frame ``i`` as :func:`each_frame` numbers it), and the rate the header gives
    (frames a second, 0 where it gives none); None where the packets carry no timestamps.
    Raises ParaDriveError naming the file when it cannot be read."""
    import av

    path = Path(path)
    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise ParaDriveError(f"{path}: no video stream; give a video file")
            stream = container.streams.video[0]
            rate = float(stream.average_rate or stream.guessed_rate or 0)
            stamps = _presented(container, stream)
            base = stream.time_base
    except MemoryError:
        raise
    except (av.error.FFmpegError, OSError) as exc:
        raise ParaDriveError(f"{path}: cannot read the video's timestamps ({exc}); the file is "
                             f"missing or corrupt") from exc
    if stamps is None or not stamps or base is None:
        return None
    ticks = np.asarray(stamps, dtype=np.int64) - stamps[0]
    return ticks * float(base), rate


def decode_frames(path: str | Path, indices: Sequence[int] | None = None, *,
                  size: tuple[int, int] | None = None, seek: bool = True,
                  threads: int = 1, stats: dict | None = None) -> np.ndarray:
    """Frames of a video as uint8 (F, H, W, 3) RGB, in the order of ``indices``.

    indices: 0-based frame numbers (repeats allowed): frame ``i`` is the ``i``-th the file
    presents, by its timestamps (for a constant-rate file, the one at ``i / fps``); None = every
    frame.
    size: (height, width) to resize to while converting (swscale, area filter); None = as stored.
    seek: seek to the keyframe at or before the first index (False decodes from the start; the
    result is the same, only slower).
    threads: decoder threads (1 = one, the right choice inside DataLoader workers; otherwise
    FFmpeg's frame and slice threading with that many, 0 = FFmpeg picks).
    stats: if given, ``stats["decoded"]`` is set to the number of frames the decoder produced.
    Raises ParaDriveError naming the file when it cannot be opened or is too short.
    """
    got: dict[int, np.ndarray] = {}
    order: list[int] = []

    def keep(idx: int, pixels: np.ndarray) -> None:
        got[idx] = pixels
        order.append(idx)

    each_frame(path, indices, keep, size=size, seek=seek, threads=threads, stats=stats)
    if indices is None:
        return np.stack([got[i] for i in order])
    return np.stack([got[int(i)] for i in indices])


def each_frame(path: str | Path, indices: Sequence[int] | None, sink: Callable[[int, Any], None], *,
               size: tuple[int, int] | None = None, seek: bool = True, threads: int = 1,
               stats: dict | None = None, planar: bool = False) -> None:
    """Decode the frames ``indices`` (None = all) of ``path`` and hand each to ``sink(index,
    pixels)`` once, in frame order, without holding the whole clip. Arguments as in
    ``decode_frames``.

    pixels: a uint8 (H, W, 3) RGB array; with ``planar=True`` a tuple of three uint8 (H, W)
    views (R, G, B) into the decoder's planar frame (FFmpeg ``gbrp``), valid only during the call:
    copy them straight into a channels-first buffer, no interleaved array is made. The planar
    conversion is exact at the stored size; resized (area filter) it scales each colour plane,
    which differs from the interleaved path's values at sharp edges (and is the nearer of the
    two to an exact area average of the full-size RGB frame).
    """
    path = Path(path)
    wanted = None if indices is None else sorted(set(int(i) for i in indices))
    if wanted is not None and (not wanted or wanted[0] < 0):
        raise ValueError(f"frame indices must be non-negative and non-empty, got {indices!r}")
    got = _FrameWalk(path, wanted, sink, size, stats, planar).run(seek, threads)
    if got is None:  # no timestamps to place a sought frame, or the seek overshot: start over
        got = _FrameWalk(path, wanted, sink, size, stats, planar).run(False, threads)
    if wanted is None and not got:
        raise ParaDriveError(f"{path}: video has no frames; re-run the clip stage")
    missing = [i for i in (wanted or ()) if i not in (got or ())]
    if missing:
        raise ParaDriveError(f"{path}: frames {missing[:5]} not in the video; the manifest and "
                             f"the video disagree, re-run the clip and manifest stages")


class _FrameWalk:
    """One pass of the decoder over a video, handing the wanted frames to ``sink``."""

    def __init__(self, path: Path, wanted: list[int] | None, sink: Callable[[int, Any], None],
                 size: tuple[int, int] | None, stats: dict | None, planar: bool = False):
        self.path, self.wanted, self.sink, self.size, self.stats = path, wanted, sink, size, stats
        self.planar = planar
        self.lookup = set(wanted or ())
        self.got: set[int] = set()
        self.scaler: Any = None   # one VideoReformatter (swscale context) per pass, made in run()
        self.scale_threads = 1

    def convert(self, frame) -> Any:
        """The frame as RGB through the walk's one swscale context.

        ``VideoFrame.reformat`` and ``to_ndarray(format=...)`` give every decoded frame a new
        context, and setting one up costs as much as converting a small frame: read per frame,
        that doubled the conversion's share of a 320x192 decode. One context for the walk, with
        the same arguments every frame, is set up once and gives the same pixels.
        """
        options: dict[str, Any] = {"format": "gbrp" if self.planar else "rgb24",
                                   "threads": self.scale_threads}
        if self.size is not None:
            options.update(width=self.size[1], height=self.size[0], interpolation="AREA")
        converted = self.scaler.reformat(frame, **options)
        return _rgb_planes(converted) if self.planar else converted.to_ndarray()

    def run(self, seek: bool, threads: int) -> set[int] | None:
        """The indices handed over; None when a seek landed where frames cannot be placed."""
        import av
        from av.video.reformatter import VideoReformatter

        try:
            container = av.open(str(self.path))
        except MemoryError:
            raise  # FFmpeg's ENOMEM is both: an allocation that failed is no corrupt file
        except (av.error.FFmpegError, OSError) as exc:
            raise ParaDriveError(f"{self.path}: cannot open video ({exc}); the file is missing or "
                                 f"corrupt, run `paradrive inspect --verify` on the build") from exc
        with container:
            stream = container.streams.video[0]
            # 1: one thread; otherwise frame and slice threads (0: FFmpeg picks how many)
            stream.thread_type = "SLICE" if threads == 1 else "AUTO"
            stream.codec_context.thread_count = max(0, int(threads))
            # swscale takes the decoder's thread count: left at PyAV's 0 it slices every frame
            # over all cores, which a one-thread DataLoader worker must not do
            self.scaler, self.scale_threads = VideoReformatter(), max(0, int(threads))
            try:
                return self._decode(container, stream, seek)
            except MemoryError:
                raise
            except av.error.FFmpegError as exc:
                raise ParaDriveError(f"{self.path}: video is corrupt ({exc}); re-run the clip stage "
                                     f"for its scene, or `paradrive inspect --verify` the build") from exc

    def _decode(self, container, stream, seek: bool) -> set[int] | None:
        """Decoded from the start, frame ``i`` is the ``i``-th presented; after a seek, the frame
        whose timestamp is the ``i``-th smallest of the file's packets."""
        first = 0 if self.wanted is None else self.wanted[0]
        place: dict[int, int] | None = None
        if seek and first and self.wanted is not None:
            stamps = _presented(container, stream, self.wanted[-1])
            if stamps is None or first >= len(stamps):
                return None   # nothing to seek to by timestamp: decode from the start
            place = {stamp: i for i, stamp in enumerate(stamps)}
            container.seek(stamps[first], stream=stream, backward=True, any_frame=False)
        for counter, frame in enumerate(container.decode(stream), start=1):
            if self.stats is not None:
                self.stats["decoded"] = self.stats.get("decoded", 0) + 1
            if place is None:
                idx = counter - 1
            else:
                found = place.get(frame.pts if frame.pts is not None else -1)
                if found is None or (counter == 1 and found > first):
                    # past the packets read (all wanted ones were before), or the seek overshot
                    return None if not self.got else self.got
                idx = found
            if self._take(idx, frame):
                break
        return self.got

    def _take(self, idx: int, frame) -> bool:
        """Hand frame ``idx`` over when wanted; True once nothing more is wanted."""
        if self.wanted is None:
            self.sink(idx, self.convert(frame))
            self.got.add(idx)
            return False
        if idx in self.got or idx < self.wanted[0]:
            return False
        if idx > self.wanted[-1]:
            return True
        if idx in self.lookup:
            self.sink(idx, self.convert(frame))
            self.got.add(idx)
        return len(self.got) == len(self.wanted)


def _rgb_planes(planar) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R, G, B) uint8 (H, W) views of a ``gbrp`` frame's planes (no copy)."""
    g, b, r = (np.frombuffer(p, dtype=np.uint8).reshape(p.height, p.line_size)[:, :p.width]
               for p in planar.planes)
    return r, g, b
