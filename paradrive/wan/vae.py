"""Wan2.1's 3D VAE (diffusers' ``AutoencoderKLWan``) from a local folder: encode clips to the
latents a Wan trainer diffuses in, and decode them back.

Latent convention (the one every Wan trainer caches and Wan's pipeline un-does before decoding):
the *posterior mean* of ``encode`` (no sampling, so a cache is deterministic), normalised per
channel with the VAE config's statistics, ``z = (mean - latents_mean) / latents_std``. The VAE
compresses 4x in time with the first frame a latent frame of its own (``1 + (F - 1) // 4`` latent
frames: 121 -> 31) and 8x in space, into 16 channels.

Nothing here downloads: the weights are a local diffusers folder, either the ``vae/`` folder
itself or a whole Wan2.1 diffusers folder (``vae/``, ``text_encoder/``, ``tokenizer/``,
``transformer/``).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any

import torch

from paradrive.errors import ConfigError
from paradrive.io import sha256_file

__all__ = ["LATENT_CONVENTION", "TEMPORAL_FACTOR", "SPATIAL_FACTOR", "TINY", "TINY_SEED", "tiny_vae_config",
           "make_tiny_vae", "vae_folder", "load_vae", "vae_checksum", "encode_video", "decode_latents",
           "latent_frames", "latent_shape", "folder_checksum"]

LATENT_CONVENTION = "posterior mean, (z - latents_mean) / latents_std per channel (the VAE config's)"
TEMPORAL_FACTOR = 4
SPATIAL_FACTOR = 8
# The name that stands for the tiny random VAE wherever a VAE folder is asked for (``encode --vae
# tiny``, ``model.vae: tiny`` in the smoke training config): the weights make_tiny_vae draws from
# TINY_SEED, the training configs' default seed, so a cache encoded with it fits `train --config smoke`
TINY = "tiny"
TINY_SEED = 0
_WAN_DOWNLOAD_HINT = ("pass a local folder holding the VAE's config.json and weights (diffusers' "
                      "layout, e.g. Wan2.1-T2V-1.3B-Diffusers or its vae/ folder)")


def tiny_vae_config() -> dict[str, Any]:
    """A Wan VAE small enough to run on a CPU in a test (~70k parameters) that keeps the real
    model's shape contract: 16 channels, 4x temporal (first frame alone), 8x spatial, the real
    normalisation statistics (diffusers' defaults)."""
    return {"base_dim": 8, "z_dim": 16, "dim_mult": [1, 1, 1, 1], "num_res_blocks": 1,
            "attn_scales": [], "temperal_downsample": [False, True, True], "dropout": 0.0}


def make_tiny_vae(seed: int = 0) -> Any:
    """A :func:`tiny_vae_config` VAE with random weights, the same for the same ``seed`` (the global
    RNG is left as it was), in eval mode on the CPU."""
    from diffusers import AutoencoderKLWan

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        vae: Any = AutoencoderKLWan(**tiny_vae_config())
    return vae.eval()


def vae_folder(path: str | os.PathLike) -> Path:
    """The folder holding the VAE's ``config.json``: ``path`` itself, or its ``vae/`` (a whole Wan
    diffusers folder); ConfigError naming ``path`` and the fix otherwise."""
    root = Path(path)
    if not root.is_dir():
        raise ConfigError(f"Wan VAE folder {path} does not exist or is not a folder; {_WAN_DOWNLOAD_HINT}")
    for folder in (root, root / "vae"):
        if (folder / "config.json").is_file():
            return folder
    raise ConfigError(f"Wan VAE folder {path} has no config.json (nor vae/config.json); {_WAN_DOWNLOAD_HINT}")


def load_vae(path: str | os.PathLike, device: str | torch.device = "cpu",
             dtype: torch.dtype = torch.float32) -> Any:
    """``AutoencoderKLWan`` from a local folder (see :func:`vae_folder`) on ``device`` in ``dtype``,
    in eval mode; ConfigError naming the folder when it holds no loadable Wan VAE. :data:`TINY`
    gives the tiny random VAE of the smoke configs."""
    from diffusers import AutoencoderKLWan

    if str(path) == TINY:
        return make_tiny_vae(TINY_SEED).to(device=torch.device(device), dtype=dtype).eval()
    folder = vae_folder(path)
    try:
        vae = AutoencoderKLWan.from_pretrained(folder, local_files_only=True, torch_dtype=dtype,
                                                low_cpu_mem_usage=False)
    except weight_errors() as exc:
        raise ConfigError(f"Wan VAE folder {folder} could not be loaded ({first_line(exc)}); "
                          f"{_WAN_DOWNLOAD_HINT}") from exc
    return vae.to(device=torch.device(device)).eval()


def vae_checksum(path: str | os.PathLike, seed: int = TINY_SEED) -> str:
    """What names a VAE's weights in a latent cache: the :func:`folder_checksum` of its folder, or
    for :data:`TINY` the sha256 of the tiny VAE's tensors drawn from ``seed`` (names, dtypes, shapes
    and bytes in name order)."""
    if str(path) != TINY:
        return folder_checksum(vae_folder(path))
    digest = hashlib.sha256()
    for name, tensor in sorted(make_tiny_vae(seed).state_dict().items()):
        values = tensor.detach().to("cpu").contiguous()
        digest.update(f"{name}\0{values.dtype}\0{tuple(values.shape)}\n".encode())
        digest.update(values.numpy().tobytes())
    return digest.hexdigest()


def weight_errors() -> tuple[type[BaseException], ...]:
    """What loading a model folder raises when its files are missing, damaged or cut short (a
    truncated safetensors file raises safetensors' own error, which is no OSError)."""
    from safetensors import SafetensorError

    return (OSError, ValueError, TypeError, KeyError, RuntimeError, SafetensorError)


def first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def latent_frames(frames: int) -> int:
    """Latent frames of a ``frames``-frame clip: the first frame alone, then one per 4 (121 -> 31)."""
    if frames < 1:
        raise ValueError(f"a clip needs at least one frame, got {frames}")
    return 1 + (frames - 1) // TEMPORAL_FACTOR


def latent_shape(frames: int, height: int, width: int, channels: int = 16) -> tuple[int, int, int, int]:
    """(C, T', H/8, W/8) of one clip's latents."""
    return channels, latent_frames(frames), height // SPATIAL_FACTOR, width // SPATIAL_FACTOR


def _statistics(vae: Any, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """The per-channel latent mean and std of the VAE's config, shaped (1, C, 1, 1, 1), float32."""
    channels = int(vae.config.z_dim)
    mean = torch.tensor(vae.config.latents_mean, dtype=torch.float32, device=device).view(1, channels, 1, 1, 1)
    std = torch.tensor(vae.config.latents_std, dtype=torch.float32, device=device).view(1, channels, 1, 1, 1)
    return mean, std


def _check_video(video: torch.Tensor) -> None:
    if video.ndim != 5 or video.shape[1] != 3:
        raise ValueError(f"video must be (B, 3, F, H, W), got {tuple(video.shape)}")
    height, width = video.shape[-2:]
    if height % SPATIAL_FACTOR or width % SPATIAL_FACTOR:
        raise ValueError(f"video height and width must be multiples of {SPATIAL_FACTOR}, got {height}x{width}")


@torch.no_grad()
def encode_video(vae: Any, video: torch.Tensor) -> torch.Tensor:
    """Video (B, 3, F, H, W) in [-1, 1] on the VAE's device -> normalised posterior mean
    (B, 16, 1 + (F - 1) // 4, H / 8, W / 8), float32 (whatever the VAE's dtype).

    Frames past the last whole group of 4 are dropped by the VAE, so clips of 4k + 1 frames use all.
    """
    _check_video(video)
    posterior = vae.encode(video.to(dtype=vae.dtype)).latent_dist
    mean, std = _statistics(vae, video.device)
    return (posterior.mean.float() - mean) / std


@torch.no_grad()
def decode_latents(vae: Any, latents: torch.Tensor) -> torch.Tensor:
    """The inverse of :func:`encode_video`: normalised latents (B, 16, T', h, w) -> video
    (B, 3, 1 + 4 (T' - 1), 8h, 8w) in [-1, 1], float32."""
    mean, std = _statistics(vae, latents.device)
    raw = latents.float() * std + mean
    video = vae.decode(raw.to(dtype=vae.dtype)).sample
    return video.float().clamp(-1.0, 1.0)


def folder_checksum(path: str | os.PathLike) -> str:
    """sha256 over a model folder: each file's relative POSIX name and its bytes' sha256, in sorted
    name order. Two folders with the same files give the same value wherever they live, and a
    renamed or changed weight file changes it, so a latent cache can name the weights it came from."""
    root = Path(path)
    digest = hashlib.sha256()
    files = sorted((p for p in root.rglob("*") if p.is_file()), key=lambda p: p.relative_to(root).as_posix())
    for file in files:
        digest.update(f"{file.relative_to(root).as_posix()}\0{sha256_file(file)}\n".encode())
    return digest.hexdigest()
