"""Depth as OpenEXR: one float32 channel "Z" per frame, ZIP-compressed, written atomically."""

from __future__ import annotations

import os

import numpy as np

from paradrive.io import atomic_path


def write_depth_exr(path: str | os.PathLike, depth: np.ndarray) -> None:
    """Write float32 depth (H, W) as a single-channel ("Z") ZIP-compressed OpenEXR, atomically."""
    import OpenEXR

    depth = np.ascontiguousarray(depth, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth must be (H, W), got {depth.shape}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp:
        OpenEXR.File(header, {"Z": depth}).write(str(tmp))


def read_depth_exr(path: str | os.PathLike) -> np.ndarray:
    """float32 (H, W) depth from an EXR written by :func:`write_depth_exr` (channel "Z")."""
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        channels = f.channels()
        if "Z" not in channels:
            raise ValueError(f"{path}: no 'Z' channel (has {', '.join(channels)})")
        return np.array(channels["Z"].pixels, dtype=np.float32)


