"""What a test asks of a video file beyond its pixels: codec, size, pixel format, rate, frames."""

from __future__ import annotations

import os


def probe_video(path: str | os.PathLike) -> dict:
    """Codec, size, pixel format, frame rate and the number of frames (counted by decoding)."""
    import av

    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        info = {"codec": stream.codec_context.name, "width": stream.codec_context.width,
                "height": stream.codec_context.height, "pix_fmt": stream.codec_context.pix_fmt,
                "fps": float(stream.average_rate or stream.base_rate or 0)}
        info["frames"] = sum(1 for _ in container.decode(stream))
    return info
