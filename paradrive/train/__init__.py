"""The trainers users run on a build, and what hands a build or a trained model on.

The reference flow-matching trainer, ReCamDriving's two-stage camera-controlled video model,
small: ``autoencoder`` (video <-> latents, pluggable), ``model`` (video DiT, camera encoder, frame
embedding, stage-2 Rendering / Cross Attention), ``flow`` (rectified-flow loss, Euler sampler),
``trainer`` (loop, freezing, checkpoints, exact resume, sampling). ``wan``: the same two stages on
Wan2.1's transformer (the model pieces are :mod:`paradrive.wan`'s); ``distributed``: data
parallel under torchrun. ``runs``: a run as ``paradrive train`` starts it; ``convert``: a build in
other trainers' layouts (``paradrive convert``); ``generate``: a trained model's videos of an
inference build (``paradrive generate``). Data comes only through :mod:`paradrive.data`.

Credit: the two-stage model and its schedule follow ReCamDriving (Li et al.); the camera condition
of ``pose_format="recammaster"`` follows ReCamMaster (Bai et al.); the latent shapes follow Wan2.1.
"""

from __future__ import annotations

import importlib
from typing import Any

# Imported on first use: the command line looks up ``paradrive.train.runs`` at start-up, and
# every command would otherwise pay for importing torch there.
_EXPORTS = {
    "paradrive.train.autoencoder": ("PatchAutoencoder", "VideoEncoder", "make_autoencoder"),
    "paradrive.train.flow": ("euler_sample", "flow_matching_loss", "interpolate", "sample_times"),
    "paradrive.train.model": ("CameraEncoder", "ModelConfig", "VideoDiT", "is_stage2_parameter"),
    "paradrive.train.trainer": ("Trainer", "load_config", "load_for_sampling", "sample_video", "write_video"),
}
_WHERE = {name: module for module, names in _EXPORTS.items() for name in names}
__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    if name not in _WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(_WHERE[name]), name)
