"""``paradrive train --model wan``: ReCamDriving's two stages on Wan2.1 (:mod:`paradrive.wan.recam`).

:class:`WanTrainer` is the reference trainer (:class:`paradrive.train.trainer.Trainer`) with the
Wan model in place of the compact DiT: the loop, the data order, the processes, the learning
rate and the exact resume are the reference's own; what differs is how a batch becomes the
model's inputs (:class:`WanRunner`, shared with generation), how the model is built and what a
checkpoint holds: the parameters trained so far, their optimiser state and the counters, beside
the base transformer's folder and a fingerprint of its config, never the frozen base weights.

A batch comes in one of two forms, told apart by its keys:

* latents (a build with cached latents, ``paradrive encode``): ``target_latents``,
  ``source_latents``, ``condition_latents`` (B, 16, T', h, w), ``camera`` (B, T', 12) and
  ``text_embedding`` (B, L, D), read as they are;
* pixels (any build): ``target`` / ``source`` / ``condition`` frames, encoded here by the VAE
  (frozen, no gradients), the camera taken from ``rel_pose`` at frames 0, 4, 8, ... (one per
  latent frame) and the empty prompt's embedding computed once.

The camera input (``model.camera``, :data:`CAMERA_FORMS`): ``relative`` is ΔT = ``rel_pose`` =
inv(c2w_target)·c2w_source at the same frame, the map from source-camera to target-camera
coordinates; ``recammaster_per_frame`` is its inverse, inv(c2w_source)·c2w_target at the same
frame, the target camera seen from the source camera in ReCamMaster's sign; ``recammaster`` is
the target camera in the source camera's coordinates at its first frame, ReCamMaster's own form,
which carries the ego's own motion too. ``auto`` (the default) is ``recammaster_per_frame`` when
stage 1 starts its camera encoder from ReCamMaster (``model.recammaster``), so the encoder reads
inputs of the sign it was trained on, and ``relative`` otherwise; stage 2 keeps the form its
stage-1 checkpoint was trained with. The run's config and checkpoints record the form used, never
``auto`` (see docs/train-recamdriving.md).
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any, cast

import torch

from paradrive import geometry
from paradrive.data import PairDataset
from paradrive.errors import ConfigError, ParaDriveError
from paradrive.io import load_tensors
from paradrive.train.flow import Generators, euler_sample, flow_matching_loss
from paradrive.train.trainer import (CHECKPOINT_KEYS, DamagedCheckpoint, Trainer, collate, frames_on, load_config,
                                     read_checkpoint)
from paradrive.latents import has_latents, latents_index_path, read_latents_index
from paradrive.wan.recam import (ReCamDrivingWan, checkpoint_parameter_names, config_fingerprint, load_recammaster,
                                 load_trained, load_transformer, make_tiny_transformer, trainable_parameters)

log = logging.getLogger(__name__)

# /3: the frame embedding counts the latent frames of one clip (shared by target, source and
# condition); a /2 checkpoint's covered the joined sequence and does not fit
CHECKPOINT_FORMAT = "paradrive-train-wan/3"
TINY = "tiny"
TINY_TEXT_TOKENS = 8
# model settings a stage-2 run may set apart from the stage-1 run it starts from
_STAGE_ONLY = ("stage2_ffn", "recammaster", "cross_attn_zero_out")
# the camera inputs ``model.camera`` chooses among (besides ``auto``)
CAMERA_FORMS = ("relative", "recammaster_per_frame", "recammaster")


def load_wan_config(source: str | Path | None, overrides: Mapping[str, Any] | None = None) -> dict:
    """A ``--model wan`` training config: a config name ``NAME`` means ``stages/train/wan-NAME.yaml``
    (``smoke`` -> ``wan-smoke``, none -> ``wan-default``); a YAML path is read as it is."""
    name = "default" if source is None else str(source)
    if not Path(name).suffix and not Path(name).exists() and not name.startswith("wan-"):
        name = f"wan-{name}"
    return load_config(name, overrides)


def latent_frame_indices(frames: int) -> list[int]:
    """The video frame standing for each latent frame of a ``frames``-frame clip: 0, 4, 8, ...
    (Wan's VAE keeps the first frame alone, then one latent frame per 4)."""
    return list(range(0, frames, 4))[: 1 + (frames - 1) // 4]


def generated_frames(frames: int) -> int:
    """Frames the VAE decodes from the latents of a ``frames``-frame clip: 1 + 4 (T' - 1)."""
    return 1 + 4 * (len(latent_frame_indices(frames)) - 1)


def relative_camera(rel_pose: torch.Tensor) -> torch.Tensor:
    """ΔT per latent frame as the camera encoder reads it: rel_pose (B, F, 4, 4) -> (B, T', 12),
    the top 3x4 rows of frames 0, 4, 8, ... flattened row-major, float32."""
    index = torch.tensor(latent_frame_indices(rel_pose.shape[1]), dtype=torch.long, device=rel_pose.device)
    return rel_pose[:, index, :3, :4].reshape(rel_pose.shape[0], -1, 12).float()


def camera_form(model: Mapping[str, Any]) -> str:
    """The camera input a run's ``model`` settings choose: ``model.camera``, with ``auto`` read as
    ``recammaster_per_frame`` when ``model.recammaster`` names a ReCamMaster checkpoint (its camera
    encoder was trained on inputs of that sign) and ``relative`` otherwise."""
    chosen = str(model["camera"])
    if chosen != "auto":
        return chosen
    return "recammaster_per_frame" if model.get("recammaster") is not None else "relative"


def to_channels_first(frames: torch.Tensor) -> torch.Tensor:
    """The adapter's (B, F, 3, H, W) frames -> the (B, 3, F, H, W) layout diffusers' video models
    (and the Wan VAE) take."""
    return frames.permute(0, 2, 1, 3, 4)


def check_shape(config: Mapping[str, Any], model: ReCamDrivingWan) -> None:
    """ConfigError before any work when the frame embedding cannot cover a clip's latent frames,
    or the frames do not divide into the transformer's patches."""
    d = config["data"]
    frames, cover = int(d["num_frames"]), int(config["model"]["max_frames"])
    need = len(latent_frame_indices(frames))
    if need > cover:
        raise ConfigError(f"model.max_frames = {cover}: {frames}-frame clips need {need} (their latent frames, "
                          f"1 + (F - 1) // 4); set model.max_frames={need} or more")
    _, p_h, p_w = model.transformer.config.patch_size
    unit_h, unit_w = 8 * p_h, 8 * p_w   # the VAE's 8x, then the transformer's patch
    if int(d["height"]) % unit_h or int(d["width"]) % unit_w:
        raise ConfigError(f"data.height x data.width = {d['height']}x{d['width']}: the VAE's 8x and the "
                          f"transformer's {p_h}x{p_w} patch need multiples of {unit_h}x{unit_w} (e.g. 480x832)")


# -- the build's pairs ---------------------------------------------------------------------------
def cache_mismatch(build_dir: str | Path, config: Mapping[str, Any]) -> str | None:
    """Why the build's latent cache cannot feed this run (its frames, size or VAE differ from the
    config's, or it is unreadable), as what follows "the cache" in a sentence; None when it fits."""
    from paradrive.wan.vae import vae_checksum

    d = config["data"]
    try:
        doc = read_latents_index(build_dir)
    except ParaDriveError as exc:
        return f"cannot be read ({exc})"
    differ = []
    if int(doc["num_frames"]) != int(d["num_frames"]):
        differ.append(f"{doc['num_frames']} frames, this run reads {d['num_frames']} (data.num_frames)")
    if [int(v) for v in doc["size"]] != [int(d["height"]), int(d["width"])]:
        differ.append(f"{doc['size'][0]}x{doc['size'][1]}, this run reads {d['height']}x{d['width']} "
                      f"(data.height x data.width)")
    if int(d["frame_stride"]) != 1:
        differ.append(f"every frame, this run reads every {d['frame_stride']}th (data.frame_stride)")
    vae = config["model"]["vae"]
    if vae is not None:
        own = vae_checksum(vae, int(config["seed"]))
        if own != doc["vae"]["sha256"]:
            differ.append(f"by the VAE in {doc['vae']['path']} (sha256 {doc['vae']['sha256'][:12]}…), this run's "
                          f"model.vae {vae} is another (sha256 {own[:12]}…)")
    return "; ".join(f"was encoded {d}" if d.startswith("by ") else f"was encoded at {d}" for d in differ) or None


def open_wan_dataset(build_dir: str | Path, config: Mapping[str, Any], notes: list[str] | None = None) -> PairDataset:
    """The build's pairs as the trainer reads them: cached latents (``latents=True``) when
    ``data.input`` asks for them or is ``auto`` and the build has a cache that fits the config
    (:func:`cache_mismatch`), else uint8 frames. ``data.input: latents`` with no fitting cache is
    a ConfigError; ``auto`` then reads the videos and says why in ``notes``."""
    d = config["data"]
    pose_format = "recammaster" if camera_form(config["model"]) == "recammaster" else None
    kwargs: dict[str, Any] = {"num_frames": d["num_frames"], "frame_stride": d["frame_stride"],
                              "output_size": (d["height"], d["width"]), "pose_format": pose_format}
    fix = (f"re-encode it with 'paradrive encode {build_dir} --vae DIR --set encode.num_frames={d['num_frames']} "
           f"--set encode.size=[{d['height']},{d['width']}]', or set data.input=pixels")
    if d["input"] != "pixels" and has_latents(build_dir):
        why = cache_mismatch(build_dir, config)
        if why is None:
            return PairDataset(build_dir, latents=True, dtype="float32")
        where = latents_index_path(build_dir)
        if d["input"] == "latents":
            raise ConfigError(f"--build {build_dir}: its latent cache ({where}) {why}; {fix}")
        if notes is not None:
            notes.append(f"--build {build_dir}: its latent cache ({where}) {why}; encoding the videos on "
                         f"the fly instead (data.input=auto); to train from the cache, {fix.split(', or ')[0]}")
    elif d["input"] == "latents":
        raise ConfigError(f"--build {build_dir}: data.input=latents but the build has no cached latents; "
                          f"run 'paradrive encode {build_dir} --vae DIR' first, or use data.input=pixels")
    return PairDataset(build_dir, dtype="uint8", **kwargs)


# -- a batch as the model's inputs, and sampling ---------------------------------------------------
class WanRunner:
    """A stage's :class:`ReCamDrivingWan` with what turns a batch into its inputs (the VAE and
    the empty prompt's embedding, loaded on first use) and samples videos from it: what
    training and generation share."""

    config: dict
    stage: int
    device: torch.device
    model: Any

    def _setup_inputs(self) -> None:
        self.autocast = _autocast_dtype(self.config["precision"], self.device)
        self._vae: Any = None
        self._text: torch.Tensor | None = None

    @property
    def wan(self) -> ReCamDrivingWan:
        """The model, typed as what it is (the reference trainer's attribute names a VideoDiT)."""
        return cast(ReCamDrivingWan, self.model)

    def forward(self, *inputs: Any) -> torch.Tensor:
        return self.model(*inputs)

    def vae(self) -> Any:
        """The frozen VAE (``model.vae``), loaded on first use: a latent build never needs it."""
        if self._vae is None:
            self._vae = load_wan_vae(self.config, self.device)
        return self._vae

    def text_embedding(self, batch_size: int) -> torch.Tensor:
        """The empty prompt's embedding (``model.text_encoder``) for a pixel batch: (B, L, D)."""
        if self._text is None:
            self._text = empty_text_embedding(self.config, int(self.wan.transformer.config.text_dim))
        return self._text.to(self.device).expand(batch_size, -1, -1)

    def latents(self, batch: Mapping[str, Any]) -> dict[str, torch.Tensor]:
        """A batch as the model's inputs: target / source (/ condition) latents (B, C, T', h, w),
        ``camera`` (B, T', 12) float32 and ``text`` (B, L, D)."""
        # an inference row has no target: sampling needs only the source (and condition)
        roles = [r for r in ("target", "source", "condition")
                 if (r != "condition" or self.stage == 2) and (r != "target" or "target" in batch
                                                                or "target_latents" in batch)]
        if "source_latents" in batch:
            out = {role: batch[f"{role}_latents"].to(self.device).float() for role in roles}
            out["camera"] = self._camera(batch, cached=True)
            out["text"] = batch["text_embedding"].to(self.device).float()
            return out
        from paradrive.wan.vae import encode_video

        vae = self.vae()
        out = {role: encode_video(vae, to_channels_first(frames_on(batch[role], self.device))) for role in roles}
        out["camera"] = self._camera(batch, cached=False)
        out["text"] = self.text_embedding(out["source"].shape[0])
        return out

    def _camera(self, batch: Mapping[str, Any], cached: bool) -> torch.Tensor:
        """(B, T', 12) float32 per latent frame: ΔT (``relative``; a latent sample's ``rel_pose``
        is already one per latent frame, a pixel sample's one per video frame), its inverse
        (``recammaster_per_frame``), or ReCamMaster's form (``recammaster``: the ``camera`` of a
        latent sample or of ``pose_format="recammaster"``)."""
        form = camera_form(self.config["model"])
        if form == "recammaster":
            if "camera" not in batch:
                raise ValueError("model.camera=recammaster: the samples carry no 'camera'; read the build "
                                 "with pose_format='recammaster'")
            return batch["camera"].to(self.device).float()
        rel = batch["rel_pose"]
        if form == "recammaster_per_frame":
            if not cached:
                rel = rel[:, latent_frame_indices(rel.shape[1])]
            rows = geometry.recammaster_per_frame_camera(rel.detach().cpu().double().numpy())
            return torch.from_numpy(rows).to(self.device)
        rel = rel.to(self.device)
        if cached:
            return rel[:, :, :3, :4].reshape(rel.shape[0], rel.shape[1], 12).float()
        return relative_camera(rel)

    def _autocast(self) -> contextlib.AbstractContextManager:
        if self.autocast is None:
            return contextlib.nullcontext()
        return torch.autocast(self.device.type, dtype=self.autocast)

    def loss(self, z: Mapping[str, torch.Tensor], generator: Generators) -> torch.Tensor:
        """Flow-matching loss on the target latents (noise and times from ``generator``: one, or
        one per sample); the source (and condition) latents stay clean."""
        f = self.config["flow"]

        def velocity(x_t, t):
            return self.forward(x_t, t, z["source"], z["camera"], z["text"], z.get("condition")).float()

        with self._autocast():
            return flow_matching_loss(velocity, z["target"], generator, f["schedule"], float(f["shift"]),
                                      f["weighting"])

    @torch.no_grad()
    def sample(self, item: Mapping[str, Any], steps: int, seed: int = 0) -> torch.Tensor:
        """Generate the target video of one pair dict (as the adapter gives it) from its source,
        camera and (stage 2) condition; decoded by the VAE: (F, 3, H, W) in [-1, 1]."""
        from paradrive.wan.vae import decode_latents

        was_training = self.model.training
        self.model.eval()
        z = self.latents(collate([dict(item)]))
        noise = torch.randn(z["source"].shape, generator=torch.Generator().manual_seed(seed),
                            device="cpu").to(self.device)
        with self._autocast():
            latents = euler_sample(
                lambda x, t: self.model(x, t, z["source"], z["camera"], z["text"], z.get("condition")).float(),
                noise, steps, float(self.config["flow"]["shift"]))
        video = decode_latents(self.vae(), latents)[0].permute(1, 0, 2, 3)
        self.model.train(was_training)
        return video.clamp(-1, 1).cpu()


# -- the trainer -----------------------------------------------------------------------------------
class WanTrainer(WanRunner, Trainer):
    """Trains one stage of :class:`ReCamDrivingWan` on a map-style dataset of pair dicts (pixel or
    latent samples). ``init``: for stage 2, the stage-1 checkpoint (default: none, an error);
    for stage 1, a checkpoint of this trainer to start from. A ``last.pt`` in ``out_dir`` wins."""

    checkpoint_format = CHECKPOINT_FORMAT
    checkpoint_keys = (*CHECKPOINT_KEYS, "base")
    resume_keys = ("model", "seed")
    forward = Trainer.forward   # through DDP in a run of several processes

    def __init__(self, config: Mapping[str, Any], stage: int, out_dir: str | Path, dataset,
                 init: str | Path | None = None):
        # the reference's __init__ builds its own model: only its first steps are shared
        self._start(config, stage, out_dir, dataset)
        m = self.config["model"]
        # recorded as the form used; at stage 2 ``auto`` becomes the form stage 1 trained with
        self._camera_auto = m["camera"] == "auto"
        m["camera"] = camera_form(m)
        self.ffn = bool(m["stage2_ffn"])
        self.model = build_wan_model(self.config, stage).to(self.device)
        check_shape(self.config, self.wan)
        self.wan.enable_gradient_checkpointing(bool(m["gradient_checkpointing"]))
        self.base = base_record(self.config, self.wan)
        self._setup_inputs()
        if self._restore(stage, init) and m["recammaster"] is not None:
            self._init_from_recammaster(Path(m["recammaster"]))
        self._make_optimizer(trainable_parameters(self.wan, stage, self.ffn))

    # -- checkpoints of what trains --------------------------------------------------------------
    def model_state(self) -> dict[str, torch.Tensor]:
        """The parameters trained so far (:func:`checkpoint_parameter_names`), not the base's."""
        names = checkpoint_parameter_names(self.wan, self.stage, self.ffn)
        return {n: p.detach() for n, p in self.wan.named_parameters() if n in names}

    def state_dict(self) -> dict:
        return {**super().state_dict(), "base": dict(self.base)}

    def _load(self, path: Path, ckpt: dict) -> None:
        if ckpt.get("format") == "paradrive-train-wan/2":
            check_format(ckpt["format"], str(path))
        self._adopt_camera(ckpt, str(path))
        super()._load(path, ckpt)

    def _adopt_camera(self, ckpt: Mapping[str, Any], where: str) -> None:
        """At stage 2, ``model.camera: auto`` is the camera form of the checkpoint it starts from
        (stage 1's: its camera encoder, frozen now, was trained on that input)."""
        theirs = ckpt.get("config", {}).get("model", {}).get("camera")
        if not self._camera_auto or self.stage != 2 or theirs not in CAMERA_FORMS:
            return
        if theirs == "recammaster" and self.config["model"]["camera"] != theirs:
            raise ConfigError(f"{where}: trained with model.camera=recammaster, which reads the build with "
                              f"pose_format='recammaster'; pass --set model.camera=recammaster")
        self.config["model"]["camera"] = theirs

    def _load_model_state(self, path: Path, ckpt: dict) -> None:
        check_base(ckpt, self.base, str(path))
        load_trained(self.wan, ckpt["model"], checkpoint_parameter_names(self.wan, self.stage, self.ffn), str(path))

    def _init_from(self, path: Path) -> None:
        if not path.is_file():
            raise FileNotFoundError(f"--init {path}: no such checkpoint")
        ckpt = read_checkpoint(path, "--init", ("format", "stage", "config", "model", "base"), self.device)
        check_format(ckpt["format"], f"--init {path}")
        self._adopt_camera(ckpt, f"--init {path}")
        mine = {k: v for k, v in self.config["model"].items() if k not in _STAGE_ONLY}
        theirs = {k: v for k, v in ckpt["config"]["model"].items() if k not in _STAGE_ONLY}
        if theirs != mine:
            raise ValueError(f"--init {path}: its model settings {theirs} differ from this run's {mine}; use the "
                             f"same config, --transformer and --vae")
        check_base(ckpt, self.base, f"--init {path}")
        names = checkpoint_parameter_names(self.wan, int(ckpt["stage"]), bool(ckpt["config"]["model"]["stage2_ffn"]))
        load_trained(self.wan, ckpt["model"], names, f"--init {path}")
        log.info("initialised from %s", path)

    def _init_from_recammaster(self, path: Path) -> None:
        if not path.is_file():
            raise FileNotFoundError(f"model.recammaster {path}: no such checkpoint")
        state: Any
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            state = load_file(str(path), device="cpu")
        else:
            state = load_tensors(path)
            state = state.get("state_dict", state) if isinstance(state, dict) else state
        count = load_recammaster(self.wan, state, str(path))
        camera = self.config["model"]["camera"]
        log.info("loaded %d ReCamMaster tensors from %s (camera input: %s)", count, path, camera)
        if camera == "relative":
            self.notes.append(f"model.recammaster {path} with model.camera=relative: its camera encoder was trained "
                              f"on the target seen from the source, the opposite sign of ΔT; "
                              f"model.camera=recammaster_per_frame (the default with model.recammaster) feeds it that")


def check_format(found: Any, where: str) -> None:
    """ValueError unless ``found`` is this trainer's checkpoint format; one of the earlier format
    (its frame embedding covered the joined sequence) is named as such."""
    if found == CHECKPOINT_FORMAT:
        return
    if found == "paradrive-train-wan/2":
        raise ValueError(f"{where}: written by an earlier 'paradrive train --model wan' whose frame embedding "
                         f"covered the target's and the source's latent frames together ({found}); this one shares "
                         f"one row per latent frame ({CHECKPOINT_FORMAT}): train the stages again")
    raise ValueError(f"{where}: not a 'paradrive train --model wan' checkpoint ({CHECKPOINT_FORMAT})")


def base_record(config: Mapping[str, Any], model: ReCamDrivingWan) -> dict[str, str]:
    """What a checkpoint says of its base weights: the folder (``model.transformer``) and the
    fingerprint of the transformer's config."""
    return {"folder": str(config["model"]["transformer"]), "config_sha256": config_fingerprint(model.transformer)}


def check_base(ckpt: Mapping[str, Any], base: Mapping[str, str], where: str) -> None:
    """ValueError naming the checkpoint's base folder when ``base`` (this run's) has another config."""
    theirs = ckpt["base"]
    if theirs.get("config_sha256") != base["config_sha256"]:
        raise ValueError(f"{where}: its parameters were trained on the transformer in {theirs.get('folder')} "
                         f"(config sha256 {str(theirs.get('config_sha256'))[:12]}…), and model.transformer "
                         f"{base['folder']} has another config (sha256 {base['config_sha256'][:12]}…); pass "
                         f"--transformer {theirs.get('folder')}")


def build_wan_model(config: Mapping[str, Any], stage: int) -> ReCamDrivingWan:
    """The stage's model: the transformer (``model.transformer``: a folder, or ``tiny``) with the
    ReCamDriving modules, the new ones drawn from the config's seed."""
    m = config["model"]
    source = m["transformer"]
    if source is None:
        raise ConfigError("model.transformer is not set: pass --transformer DIR (the Wan2.1-T2V-1.3B "
                          "diffusers folder), or --set model.transformer=tiny for a tiny random model")
    transformer = make_tiny_transformer(int(config["seed"])) if source == TINY else load_transformer(source)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(config["seed"]))
        return ReCamDrivingWan(transformer, rendering=stage == 2, max_frames=int(m["max_frames"]),
                               frame_embedding=str(m["frame_embedding"]),
                               cross_attn_zero_out=bool(m["cross_attn_zero_out"]))


def load_wan_vae(config: Mapping[str, Any], device: torch.device) -> Any:
    """The VAE ``model.vae`` names (a folder, or ``tiny``), frozen, on ``device``."""
    from paradrive.wan.vae import load_vae, make_tiny_vae

    source = config["model"]["vae"]
    if source is None:
        raise ConfigError("model.vae is not set: pass --vae DIR (the Wan2.1 VAE or the whole diffusers "
                          "folder) to encode a pixel build or decode samples, or encode the build with "
                          "'paradrive encode' first")
    vae = make_tiny_vae(int(config["seed"])).to(device) if source == TINY else load_vae(source, device)
    return vae.requires_grad_(False).eval()


def empty_text_embedding(config: Mapping[str, Any], text_dim: int) -> torch.Tensor:
    """The empty prompt's embedding (L, D) float32 on the CPU: umT5's from ``model.text_encoder``,
    or, for ``tiny``, a fixed random one drawn from the seed (what a tiny transformer reads)."""
    source = config["model"]["text_encoder"]
    if source is None:
        raise ConfigError("model.text_encoder is not set: pass --text-encoder DIR (umT5 of the Wan2.1 "
                          "diffusers folder) for a pixel build, or encode the build with 'paradrive encode'")
    from paradrive.wan.text import empty_prompt_embedding, tiny_text_embedding

    if source == TINY:
        return tiny_text_embedding(int(config["seed"]), text_dim, TINY_TEXT_TOKENS)

    embedding = empty_prompt_embedding(source, "cpu")
    if embedding.shape[-1] != text_dim:
        raise ConfigError(f"model.text_encoder {source}: its embedding has {embedding.shape[-1]} channels, "
                          f"the transformer reads {text_dim}; use the text encoder of the same Wan folder")
    return embedding


def _autocast_dtype(precision: str, device: torch.device) -> torch.dtype | None:
    """bf16 autocast on CUDA (``auto`` or ``bf16``), none (fp32) otherwise."""
    if precision == "bf16" or (precision == "auto" and device.type == "cuda"):
        return torch.bfloat16
    return None


__all__ = ["CAMERA_FORMS", "CHECKPOINT_FORMAT", "DamagedCheckpoint", "WanRunner", "WanTrainer", "base_record",
           "build_wan_model", "cache_mismatch", "camera_form", "check_base", "check_format", "check_shape",
           "empty_text_embedding", "generated_frames", "latent_frame_indices", "load_wan_config", "load_wan_vae",
           "open_wan_dataset", "relative_camera", "to_channels_first"]
