"""Reference flow-matching trainer: ReCamDriving's two-stage camera-controlled video model, small.

``autoencoder`` (video <-> latents, pluggable), ``model`` (video DiT, camera encoder, frame
embedding, stage-2 Rendering / Cross Attention), ``flow`` (rectified-flow loss, Euler sampler),
``trainer`` (loop, freezing, checkpoints, exact resume, sampling), ``cli`` (``paradrive train``).
Data comes only through :mod:`paradrive.data`.

Credit: the two-stage model and its schedule follow ReCamDriving (Li et al.); the camera condition
of ``pose_format="recammaster"`` follows ReCamMaster (Bai et al.); the latent shapes follow Wan2.1.
"""

from paradrive.train.autoencoder import PatchAutoencoder, VideoEncoder, make_autoencoder
from paradrive.train.flow import euler_sample, flow_matching_loss, interpolate, sample_times
from paradrive.train.model import CameraEncoder, ModelConfig, VideoDiT, is_stage2_parameter
from paradrive.train.trainer import Trainer, load_config, load_for_sampling, sample_video, write_video

__all__ = [
    "CameraEncoder", "ModelConfig", "PatchAutoencoder", "Trainer", "VideoDiT", "VideoEncoder",
    "euler_sample", "flow_matching_loss", "interpolate", "is_stage2_parameter", "load_config",
    "load_for_sampling", "make_autoencoder", "sample_times", "sample_video", "write_video",
]
