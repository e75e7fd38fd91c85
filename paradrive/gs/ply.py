"""Standard 3DGS PLY files (the layout of the reference implementation and common viewers).

Binary little-endian, one ``vertex`` element of float32 properties in this order::

    x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 .. f_rest_{3(K-1)-1} opacity
    scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3

Values are pre-activation (log scales, opacity logits, unnormalised w x y z quaternions).
``f_rest`` is channel-major: all K-1 red coefficients, then green, then blue.
The header is written by hand so that equal parameters give byte-identical files.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from paradrive.errors import SceneError
from paradrive.io import atomic_path

from .model import Gaussians, num_sh_bases

__all__ = ["save_ply", "load_ply", "load_checkpoint", "ply_property_names"]


def ply_property_names(sh_degree: int) -> list[str]:
    """Property names of a degree-``sh_degree`` 3DGS PLY, in file order."""
    n_rest = 3 * (num_sh_bases(sh_degree) - 1)
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(n_rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def _to_numpy(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().to(torch.float32).numpy()


def params_to_array(params: Gaussians) -> np.ndarray:
    """(N, P) float32 rows in PLY property order."""
    n = params["means"].shape[0]
    shn = _to_numpy(params["shN"])                      # (N, K-1, 3)
    f_rest = shn.transpose(0, 2, 1).reshape(n, -1)      # channel-major
    cols = [_to_numpy(params["means"]), np.zeros((n, 3), np.float32),
            _to_numpy(params["sh0"]).reshape(n, 3), f_rest,
            _to_numpy(params["opacities"]).reshape(n, 1), _to_numpy(params["scales"]),
            _to_numpy(params["quats"])]
    return np.ascontiguousarray(np.concatenate(cols, 1), dtype="<f4")


def save_ply(path: str | os.PathLike, params: Gaussians) -> Path:
    """Write ``params`` (see :mod:`paradrive.gs.model`) as a 3DGS PLY, atomically."""
    path = Path(path)
    k = 1 + params["shN"].shape[1]
    degree = int(round(k ** 0.5)) - 1
    names = ply_property_names(degree)
    data = params_to_array(params)
    assert data.shape[1] == len(names), (data.shape, len(names))
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {data.shape[0]}"]
    header += [f"property float {name}" for name in names]
    header += ["end_header"]
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(("\n".join(header) + "\n").encode("ascii"))
            f.write(data.tobytes())
            f.flush()
            os.fsync(f.fileno())
    return path


def load_ply(path: str | os.PathLike) -> dict[str, torch.Tensor]:
    """Read a 3DGS PLY into raw parameters: means (N,3), scales (N,3) log, quats (N,4) wxyz,
    opacities (N,) logit, sh0 (N,1,3), shN (N,K-1,3). Any standard 3DGS PLY (any SH degree,
    ascii or binary, extra properties ignored) is accepted."""
    from plyfile import PlyData

    path = Path(path)
    ply = PlyData.read(str(path))
    v = ply["vertex"]
    names = [p.name for p in v.properties]
    n = v.count

    def cols(keys: list[str]) -> np.ndarray:
        if not keys:
            return np.zeros((n, 0), np.float32)
        return np.stack([np.asarray(v[k], dtype=np.float32) for k in keys], 1)

    for needed in ("x", "y", "z", "f_dc_0", "opacity", "scale_0", "rot_0"):
        if needed not in names:
            raise ValueError(f"{path}: not a 3DGS PLY (no '{needed}' property)")
    rest = sorted((p for p in names if p.startswith("f_rest_")), key=lambda s: int(s.split("_")[-1]))
    n_rest = len(rest)
    if n_rest % 3:
        raise ValueError(f"{path}: {n_rest} f_rest properties is not a multiple of 3")
    f_rest = cols(rest).reshape(n, 3, n_rest // 3).transpose(0, 2, 1)  # (N, K-1, 3)
    return {
        "means": torch.from_numpy(cols(["x", "y", "z"])),
        "scales": torch.from_numpy(cols(["scale_0", "scale_1", "scale_2"])),
        "quats": torch.from_numpy(cols(["rot_0", "rot_1", "rot_2", "rot_3"])),
        "opacities": torch.from_numpy(cols(["opacity"])[:, 0].copy()),
        "sh0": torch.from_numpy(cols(["f_dc_0", "f_dc_1", "f_dc_2"])[:, None, :].copy()),
        "shN": torch.from_numpy(np.ascontiguousarray(f_rest)),
    }


def load_checkpoint(path: str | os.PathLike, *, scene_id: str | None = None) -> dict:
    """Gaussian parameters of a 3DGS PLY checkpoint; a file that cannot be read is a SceneError
    naming it and the fix."""
    path = Path(path)
    try:
        return load_ply(path)
    except (OSError, ValueError, KeyError) as exc:
        raise SceneError(f"checkpoint cannot be read: {type(exc).__name__}: {exc}",
                         scene_id=scene_id, path=path, fix="re-run the fit stage") from exc
