"""ReCamDriving on diffusers' Wan2.1 transformer: the camera-conditioned, two-stage denoiser.

:class:`ReCamDrivingWan` keeps a ``diffusers.WanTransformer3DModel`` untouched (its weights load
and save in diffusers' layout) and adds, beside it, what the paper adds:

stage 1 (relative-pose control), the paper's x_i = Cat(x_t + c_r + E_f, x_s + c_I + E_f)
    per block a camera encoder (``Linear(12, dim)``, zero-initialised) whose output is added to
    the normalised hidden states entering the block's self-attention, and a projector
    (``Linear(dim, dim)``, initialised to the identity) after it, as ReCamMaster does; a learnable
    frame embedding E_f of one row per latent frame of a clip (zero-initialised). The transformer
    reads the noisy target latents and the clean source latents concatenated along frames
    (target first, as ReCamMaster orders them, so its weights keep their RoPE positions); the
    camera input is the target's pose (c_r) for the target half and the identity (c_I) for the
    source half, and target frame k and source frame k get the same row k of E_f.
stage 2 (3DGS guidance), the paper's x̄_gs = x_gs + c_r + E_f
    per block a *rendering attention* (self-attention over the condition rendering's tokens,
    a second stream carried from block to block, initialised from the block's Wan2.1
    self-attention) and a *cross attention* from the diffusion tokens to that stream, initialised
    with its norm from the block's Wan2.1 cross attention (the one to the text), as the paper
    does. The condition tokens get row k of E_f, and c_r enters them as it enters the target's:
    added to the input of every block's (rendering) attention.

Two settings beyond the paper (``frame_embedding="per_half"``, ``cross_attn_zero_out=True``) are
described where the class takes them.

Time convention: :mod:`paradrive.train.flow` runs t = 0 (noise) -> 1 (data) and learns
v = data - noise; Wan was trained on sigma = 1 - t (timestep = 1000 sigma) predicting
noise - data. :meth:`ReCamDrivingWan.forward` converts both ways, so pretrained Wan2.1 weights
see the inputs they were trained on.

Shapes: B batch, C = 16 latent channels, T' latent frames, h x w latent grid (H/8, W/8).
"""

from __future__ import annotations

import contextlib
import copy
import hashlib
import json
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any, cast

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch.utils.checkpoint import checkpoint

from paradrive.errors import ConfigError

# the identity pose as the camera encoder reads it: the top 3x4 rows, row-major
IDENTITY_CAMERA = (1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0)

# how the frame embedding's rows are laid out: the paper's one E_f for all three streams, or a row
# per frame of the joined target + source sequence (beyond the paper)
FRAME_EMBEDDINGS = ("shared", "per_half")

# module names (inside ``recam.<i>.`` or the transformer's ``blocks.<i>.``) each stage trains
STAGE1_MODULES = ("attn1", "cam_encoder", "projector", "frame_embed")
RENDERING_MODULES = ("render_norm", "render_attn", "cross_norm", "cross_attn")
STAGE2_MODULES = RENDERING_MODULES   # the paper's stage 2; ``ffn=True`` adds every block's FFN


def tiny_transformer_config() -> dict[str, Any]:
    """A WanTransformer3DModel of a few thousand parameters with Wan2.1's structure (patch 1x2x2,
    16 latent channels, RoPE over time/height/width, text cross-attention): tests and the smoke
    config run both stages on a CPU in seconds."""
    return {"patch_size": (1, 2, 2), "num_attention_heads": 2, "attention_head_dim": 12,
            "in_channels": 16, "out_channels": 16, "text_dim": 32, "freq_dim": 32, "ffn_dim": 48,
            "num_layers": 2, "cross_attn_norm": True, "qk_norm": "rms_norm_across_heads",
            "eps": 1e-6, "rope_max_seq_len": 64}


def wan21_t2v_1_3b_config() -> dict[str, Any]:
    """Wan2.1-T2V-1.3B's transformer as diffusers configures it (its ``transformer/config.json``):
    30 blocks of width 1536 (12 heads of 128), FFN 8960, umT5's 4096-wide text. For sizes and
    device checks with random weights; the real weights come from a local folder."""
    return {"patch_size": (1, 2, 2), "num_attention_heads": 12, "attention_head_dim": 128, "in_channels": 16,
            "out_channels": 16, "text_dim": 4096, "freq_dim": 256, "ffn_dim": 8960, "num_layers": 30,
            "cross_attn_norm": True, "qk_norm": "rms_norm_across_heads", "eps": 1e-6, "image_dim": None,
            "added_kv_proj_dim": None, "rope_max_seq_len": 1024}


def make_tiny_transformer(seed: int = 0):
    """The tiny transformer with random weights drawn from ``seed`` (the same every call)."""
    from diffusers import WanTransformer3DModel

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return WanTransformer3DModel(**tiny_transformer_config())


def load_transformer(path: str | Path, dtype: torch.dtype = torch.float32):
    """A WanTransformer3DModel from a local folder in diffusers' layout: a whole Wan2.1-T2V-1.3B
    diffusers folder (with ``transformer/`` inside) or the transformer folder itself.

    Built from its ``config.json`` and filled from its safetensors files (every shard of a sharded
    checkpoint) with a strict load: diffusers' own ``from_pretrained`` needs ``accelerate`` for
    this model (it keeps some modules in fp32), which a training machine may lack."""
    from diffusers import WanTransformer3DModel
    from safetensors.torch import load_file

    folder = Path(path)
    if (folder / "transformer" / "config.json").is_file():
        folder = folder / "transformer"
    files = sorted(folder.glob("*.safetensors"))
    if not (folder / "config.json").is_file() or not files:
        raise ConfigError(f"--transformer {path}: no config.json and safetensors weights there nor in "
                          f"{Path(path) / 'transformer'}; pass the Wan2.1-T2V-1.3B diffusers folder (it "
                          f"holds transformer/) or its transformer/ folder")
    model = WanTransformer3DModel.from_config(WanTransformer3DModel.load_config(str(folder)))
    state: dict[str, torch.Tensor] = {}
    for file in files:
        state.update(load_file(str(file), device="cpu"))
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()[0]
        raise ConfigError(f"--transformer {folder}: its weights do not match its config.json ({first}); "
                          f"re-copy the folder") from exc
    return model.to(dtype)


class ReCamBlockAdditions(nn.Module):
    """What ReCamDriving adds to one Wan block (the block itself stays in the transformer).

    Stage 1: ``cam_encoder`` and ``projector``. With ``rendering`` (stage 2) also
    ``render_norm`` / ``render_attn`` (a copy of the block's self-attention) and ``cross_norm`` /
    ``cross_attn`` (copies of the block's text cross attention and its norm; with
    ``cross_attn_zero_out`` the copy's output projection is zeroed)."""

    def __init__(self, block: Any, dim: int, rendering: bool, cross_attn_zero_out: bool = False):
        super().__init__()
        self.cam_encoder = nn.Linear(12, dim)
        nn.init.zeros_(self.cam_encoder.weight)
        nn.init.zeros_(self.cam_encoder.bias)
        self.projector = nn.Linear(dim, dim)
        with torch.no_grad():
            self.projector.weight.copy_(torch.eye(dim, device=self.projector.weight.device))
            self.projector.bias.zero_()
        self.rendering = rendering
        if rendering:
            if block.attn2.add_k_proj is not None:
                raise ConfigError("the transformer's cross attention also reads image tokens (added_kv_proj_dim): "
                                  "ReCamDriving's stage 2 starts from Wan2.1's text-to-video cross attention")
            self.render_norm = nn.LayerNorm(dim, eps=1e-6)
            self.render_attn = copy.deepcopy(block.attn1)    # the paper: from Wan2.1's self-attention
            self.cross_norm = copy.deepcopy(block.norm2)     # the paper: from Wan2.1's cross attention
            self.cross_attn = copy.deepcopy(block.attn2)
            if cross_attn_zero_out:
                out = cast(nn.Linear, self.cross_attn.to_out[0])
                nn.init.zeros_(out.weight)
                nn.init.zeros_(out.bias)
            self.to(block.attn1.to_q.weight.device)

    def camera(self, camera: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        """camera (B, N, 12) float32 -> (B, N, dim) in ``dtype``. The poses stay float32 into the
        encoder whatever the autocast: bf16's spacing at 100 m is 0.5 m."""
        kind = camera.device.type
        off = torch.autocast(kind, enabled=False) if torch.amp.is_autocast_available(kind) else contextlib.nullcontext()
        with off:
            out = F.linear(camera.float(), self.cam_encoder.weight.float(), self.cam_encoder.bias.float())
        return out.to(dtype)


class ReCamDrivingWan(nn.Module):
    """The ReCamDriving denoiser on a ``WanTransformer3DModel``.

    forward(x_t, t, source_latents, camera, text_embedding, condition_latents=None) -> velocity
      x_t                (B, C, T', h, w)  noisy target latents at flow time t
      t                  (B,)              flow time in [0, 1] (0 = noise, 1 = data)
      source_latents     (B, C, T', h, w)  the source video's latents
      camera             (B, T', 12)       float32 pose of the target per latent frame (see
                                           docs/train-recamdriving.md for which pose)
      text_embedding     (B, L, D)         the prompt embedding (the empty prompt's, in the paper)
      condition_latents  (B, C, T', h, w)  the 3DGS condition rendering's latents (stage 2 only)
    returns the velocity (data - noise) of the target latents, (B, C, T', h, w).

    ``max_frames``: the latent frames of one clip the frame embedding covers (the paper's f: 31
    for 121-frame clips).

    ``frame_embedding``: ``shared`` (the paper's E_f, ``max_frames`` rows: target frame k, source
    frame k and condition frame k all get row k) or ``per_half`` (beyond the paper:
    ``2 * max_frames`` rows over the joined sequence, source frame k gets row T' + k and the
    condition row k, so the embedding alone also tells the two halves apart).

    ``cross_attn_zero_out`` (beyond the paper): zero the stage-2 cross attention's output
    projection after copying it from Wan2.1's, so that a fresh stage-2 model computes exactly
    what its stage-1 weights computed. The trainer passes both from its settings.
    """

    def __init__(self, transformer: Any, rendering: bool = False, *, max_frames: int,
                 frame_embedding: str = "shared", cross_attn_zero_out: bool = False):
        super().__init__()
        if frame_embedding not in FRAME_EMBEDDINGS:
            raise ValueError(f"frame_embedding={frame_embedding!r}: use one of {', '.join(FRAME_EMBEDDINGS)}")
        self.transformer: Any = transformer
        config = transformer.config
        self.dim = int(config.num_attention_heads * config.attention_head_dim)
        self.rendering = rendering
        self.recam = nn.ModuleList(ReCamBlockAdditions(block, self.dim, rendering, cross_attn_zero_out)
                                   for block in transformer.blocks)
        device = next(transformer.parameters()).device
        self.max_frames, self.frame_embedding = int(max_frames), frame_embedding
        rows = self.max_frames * (2 if frame_embedding == "per_half" else 1)
        self.frame_embed = nn.Parameter(torch.zeros(rows, self.dim, device=device))
        self.gradient_checkpointing = False

    def enable_gradient_checkpointing(self, enabled: bool = True) -> None:
        """Recompute each block's activations in the backward pass: memory of one block instead
        of all of them, for about a third more compute (121 frames at 480x832 need it on 80 GB)."""
        self.gradient_checkpointing = enabled

    # -- tokens -------------------------------------------------------------------------------
    def frame_rows(self, frames: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The rows of E_f for the target's, the source's and the condition's ``frames`` latent
        frames, (T', dim) each: the same rows 0 .. T'-1 for all three (``shared``, the paper's),
        or rows T' .. 2T'-1 for the source (``per_half``)."""
        if frames > self.max_frames:
            raise ValueError(f"{frames} latent frames exceed model.max_frames={self.max_frames}")
        rows = self.frame_embed[:frames]
        if self.frame_embedding == "per_half":
            return rows, self.frame_embed[frames:2 * frames], rows
        return rows, rows, rows

    def _tokens(self, latents: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """latents (B, C, T, h, w) -> patch tokens (B, T*l, dim), l tokens per latent frame, each
        plus its frame's row of ``rows`` (T, dim)."""
        x = self.transformer.patch_embedding(latents)          # (B, dim, T, h', w')
        per_frame = x.shape[3] * x.shape[4]
        x = x.flatten(2).transpose(1, 2)
        e_f = rows.to(x.dtype).repeat_interleave(per_frame, dim=0)
        return (x + e_f).contiguous()

    def camera_inputs(self, camera: torch.Tensor, tokens_per_frame: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, T', 12) target poses -> what each token's camera encoder reads, repeated over each
        frame's l tokens: the joined sequence's (B, 2T'*l, 12), the target's pose on the target
        half (c_r) and the identity on the source half (c_I), and the condition's (B, T'*l, 12),
        the target's pose again (the paper's x̄_gs carries the same c_r as the target)."""
        target = camera.float().repeat_interleave(tokens_per_frame, dim=1)
        identity = torch.tensor(IDENTITY_CAMERA, dtype=torch.float32, device=camera.device)
        return torch.cat([target, identity.expand_as(target)], dim=1), target

    # -- one block ----------------------------------------------------------------------------
    def _block(self, index: int, x: torch.Tensor, cond: torch.Tensor | None, camera: torch.Tensor,
               cond_camera: torch.Tensor | None, context: torch.Tensor, temb: torch.Tensor, rope: tuple,
               cond_rope: tuple | None) -> tuple[torch.Tensor, torch.Tensor | None]:
        """One Wan block with ReCamDriving's additions, in the block's own order: self-attention
        (camera added to its input, projector on its output), [stage 2: rendering attention (the
        same camera term added to its input) and cross attention], text cross-attention, FFN."""
        block, add = self.transformer.blocks[index], cast(ReCamBlockAdditions, self.recam[index])
        shift, scale, gate, c_shift, c_scale, c_gate = (block.scale_shift_table + temb.float()).chunk(6, dim=1)
        normed = (block.norm1(x.float()) * (1 + scale) + shift).type_as(x)
        normed = normed + add.camera(camera, normed.dtype)
        attn = add.projector(block.attn1(normed, None, None, rope))
        x = (x.float() + attn * gate).type_as(x)
        if self.rendering:
            assert cond is not None and cond_camera is not None and cond_rope is not None
            normed_cond = add.render_norm(cond)
            normed_cond = normed_cond + add.camera(cond_camera, normed_cond.dtype)
            cond = cond + add.render_attn(normed_cond, None, None, cond_rope)
            x = x + add.cross_attn(add.cross_norm(x), cond, None, None)
        normed = block.norm2(x.float()).type_as(x)
        x = x + block.attn2(normed, context, None, None)
        normed = (block.norm3(x.float()) * (1 + c_scale) + c_shift).type_as(x)
        x = (x.float() + block.ffn(normed).float() * c_gate).type_as(x)
        return x, cond

    # -- forward ------------------------------------------------------------------------------
    def forward(self, x_t: torch.Tensor, t: torch.Tensor, source_latents: torch.Tensor,
                camera: torch.Tensor, text_embedding: torch.Tensor,
                condition_latents: torch.Tensor | None = None) -> torch.Tensor:
        b, _, frames, h, w = x_t.shape
        if source_latents.shape != x_t.shape:
            raise ValueError(f"source latents {tuple(source_latents.shape)} and target latents "
                             f"{tuple(x_t.shape)} differ")
        if camera.shape != (b, frames, 12):
            raise ValueError(f"camera {tuple(camera.shape)}: need one 12-number pose per latent frame "
                             f"({b}, {frames}, 12)")
        if self.rendering and condition_latents is None:
            raise ValueError("this is a stage-2 model: pass the condition rendering's latents")
        tf = self.transformer
        p_t, p_h, p_w = tf.config.patch_size
        if h % p_h or w % p_w:
            raise ValueError(f"latent grid {h}x{w} does not divide into the transformer's patch {p_h}x{p_w}")
        hidden = torch.cat([x_t, source_latents.to(x_t.dtype)], dim=2)    # target first, then source
        rope = tf.rope(hidden)
        e_target, e_source, e_condition = self.frame_rows(frames)
        x = self._tokens(hidden, torch.cat([e_target, e_source]))
        cam, cond_cam = self.camera_inputs(camera, (h // p_h) * (w // p_w))
        cond = cond_rope = None
        if self.rendering:
            assert condition_latents is not None
            if condition_latents.shape != x_t.shape:
                raise ValueError(f"condition latents {tuple(condition_latents.shape)} and target latents "
                                 f"{tuple(x_t.shape)} differ")
            cond_rope = tf.rope(condition_latents)
            cond = self._tokens(condition_latents.to(x_t.dtype), e_condition)
        sigma = (1.0 - t.float()).expand(b) if t.ndim == 0 else 1.0 - t.float()
        temb, timestep_proj, context, _ = tf.condition_embedder(sigma * 1000.0, text_embedding.to(x.dtype), None)
        timestep_proj = timestep_proj.unflatten(1, (6, -1))
        for i in range(len(tf.blocks)):
            if self.gradient_checkpointing and torch.is_grad_enabled():
                x, cond = checkpoint(self._block, i, x, cond, cam, cond_cam, context, timestep_proj, rope,
                                     cond_rope, use_reentrant=False)
            else:
                x, cond = self._block(i, x, cond, cam, cond_cam, context, timestep_proj, rope, cond_rope)
        shift, scale = (tf.scale_shift_table + temb.unsqueeze(1)).chunk(2, dim=1)
        x = (tf.norm_out(x.float()) * (1 + scale) + shift).type_as(x)
        x = tf.proj_out(x)
        out = x.reshape(b, 2 * frames // p_t, h // p_h, w // p_w, p_t, p_h, p_w, -1)
        out = out.permute(0, 7, 1, 4, 2, 5, 3, 6).flatten(6, 7).flatten(4, 5).flatten(2, 3)
        # Wan predicts noise - data; the flow module integrates data - noise
        return -out[:, :, :frames]


def _in_modules(name: str, modules: tuple[str, ...]) -> bool:
    return any(f".{m}." in f".{name}." or name == m for m in modules)


def stage_parameter_names(model: ReCamDrivingWan, stage: int, ffn: bool = False) -> set[str]:
    """The names of the parameters ``stage`` trains: the paper's sets exactly.

    Stage 1: every block's self-attention (``attn1``: q, k, v, out, q/k norms), camera encoder
    and projector, and the frame embedding. Stage 2: the rendering attention and the cross
    attention with their norms; everything stage 1 trained is frozen. ``ffn`` (stage 2 only,
    beyond the paper): every block's FFN too.
    """
    if stage not in (1, 2):
        raise ValueError(f"stage must be 1 or 2, got {stage}")
    modules = STAGE1_MODULES if stage == 1 else STAGE2_MODULES + (("ffn",) if ffn else ())
    return {n for n, _ in model.named_parameters() if _in_modules(n, modules)}


def checkpoint_parameter_names(model: ReCamDrivingWan, stage: int, ffn: bool = False) -> set[str]:
    """What a checkpoint of ``stage`` holds besides the base transformer's own weights: every
    parameter trained so far (stage 1's, and at stage 2 also stage 2's), so that the base folder
    and the checkpoint together are the whole model."""
    names = stage_parameter_names(model, 1)
    return names | stage_parameter_names(model, 2, ffn) if stage == 2 else names


def checkpoint_size(model: ReCamDrivingWan, stage: int, ffn: bool = False) -> dict[str, int]:
    """What a checkpoint of ``stage`` holds, counted: the parameters it saves (fp32, 4 bytes each)
    and the trained ones whose AdamW moments it saves (two fp32 tensors each, 8 bytes), and their
    bytes (``model`` may live on the meta device: only shapes are read)."""
    count = dict(model.named_parameters())
    saved = sum(count[n].numel() for n in checkpoint_parameter_names(model, stage, ffn))
    trained = sum(count[n].numel() for n in stage_parameter_names(model, stage, ffn))
    base = sum(p.numel() for p in model.transformer.parameters())
    return {"base": base, "saved": saved, "trained": trained, "bytes": 4 * saved + 8 * trained}


def trainable_parameters(model: ReCamDrivingWan, stage: int, ffn: bool = False) -> list[nn.Parameter]:
    """Set ``requires_grad`` on exactly the parameters ``stage`` trains (all others frozen) and
    return those, in the model's order (the optimiser's parameter order)."""
    names = stage_parameter_names(model, stage, ffn)
    params = []
    for name, p in model.named_parameters():
        p.requires_grad_(name in names)
        if name in names:
            params.append(p)
    return params


def config_fingerprint(transformer: Any) -> str:
    """sha256 of a transformer's config (its ``config.json`` values, diffusers' private keys left
    out): what a checkpoint of the parameters trained on it checks the base it is loaded onto by."""
    config = {k: v for k, v in dict(transformer.config).items() if not k.startswith("_")}
    text = json.dumps(config, sort_keys=True, separators=(",", ":"), default=list)
    return hashlib.sha256(text.encode()).hexdigest()


def load_trained(model: ReCamDrivingWan, state: Mapping[str, torch.Tensor], names: set[str], where: str) -> None:
    """Load a checkpoint's trained parameters ``state`` onto ``model`` (its base weights already
    in place): ``state`` must hold every one of ``names``, and nothing else, at this model's shapes."""
    own = dict(model.named_parameters())
    missing = sorted(names - set(state))
    unexpected = sorted(set(state) - names)
    if missing or unexpected:
        raise ValueError(f"{where}: its trained parameters do not fit this model (missing {missing[:3]}, "
                         f"unexpected {unexpected[:3]}); use the transformer and config of the run that wrote it")
    for name, value in state.items():
        if own[name].shape != value.shape:
            raise ValueError(f"{where}: {name} is {tuple(value.shape)}, this model's {tuple(own[name].shape)}; "
                             f"use the transformer and config of the run that wrote it")
    model.load_state_dict(dict(state), strict=False)


# -- ReCamMaster checkpoints ----------------------------------------------------------------------
# ReCamMaster trains DiffSynth-Studio's Wan DiT and saves the trainable parameters under
# DiffSynth's names. Only the blocks' camera encoder, projector and self-attention are there.
_RECAMMASTER_PREFIXES = ("pipe.dit.", "dit.", "model.", "module.")
_RECAMMASTER_KEYS = [
    (re.compile(r"blocks\.(\d+)\.cam_encoder\.(weight|bias)"), "recam.{0}.cam_encoder.{1}"),
    (re.compile(r"blocks\.(\d+)\.projector\.(weight|bias)"), "recam.{0}.projector.{1}"),
    (re.compile(r"blocks\.(\d+)\.self_attn\.q\.(weight|bias)"), "transformer.blocks.{0}.attn1.to_q.{1}"),
    (re.compile(r"blocks\.(\d+)\.self_attn\.k\.(weight|bias)"), "transformer.blocks.{0}.attn1.to_k.{1}"),
    (re.compile(r"blocks\.(\d+)\.self_attn\.v\.(weight|bias)"), "transformer.blocks.{0}.attn1.to_v.{1}"),
    (re.compile(r"blocks\.(\d+)\.self_attn\.o\.(weight|bias)"), "transformer.blocks.{0}.attn1.to_out.0.{1}"),
    (re.compile(r"blocks\.(\d+)\.self_attn\.norm_q\.weight"), "transformer.blocks.{0}.attn1.norm_q.weight"),
    (re.compile(r"blocks\.(\d+)\.self_attn\.norm_k\.weight"), "transformer.blocks.{0}.attn1.norm_k.weight"),
]


def recammaster_key(key: str) -> str | None:
    """The :class:`ReCamDrivingWan` parameter a ReCamMaster (DiffSynth) key names, or None for
    one outside the camera encoder, projector and self-attention.

    ``blocks.{i}.cam_encoder.*`` -> ``recam.{i}.cam_encoder.*``, ``blocks.{i}.projector.*`` ->
    ``recam.{i}.projector.*``, ``blocks.{i}.self_attn.{q,k,v,o}.*`` ->
    ``transformer.blocks.{i}.attn1.{to_q,to_k,to_v,to_out.0}.*``, ``self_attn.norm_q/norm_k`` ->
    ``attn1.norm_q/norm_k``. A ``pipe.dit.`` / ``dit.`` / ``model.`` / ``module.`` prefix (a
    Lightning or DDP wrapper's) is dropped first.
    """
    for prefix in _RECAMMASTER_PREFIXES:
        if key.startswith(prefix):
            key = key[len(prefix):]
            break
    for pattern, target in _RECAMMASTER_KEYS:
        match = pattern.fullmatch(key)
        if match:
            return target.format(*match.groups())
    return None


def map_recammaster_state_dict(state: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """A ReCamMaster checkpoint's tensors under :class:`ReCamDrivingWan`'s names (keys outside
    the camera encoder, projector and self-attention are left out)."""
    out = {}
    for key, value in state.items():
        name = recammaster_key(key)
        if name is not None:
            out[name] = value
    return out


def load_recammaster(model: ReCamDrivingWan, state: Mapping[str, torch.Tensor], where: str) -> int:
    """Copy a ReCamMaster checkpoint's camera encoders, projectors and self-attention into
    ``model``; returns how many tensors. Every mapped key must exist with the same shape."""
    mapped = map_recammaster_state_dict(state)
    if not mapped:
        raise ValueError(f"{where}: no ReCamMaster key (blocks.<i>.cam_encoder / projector / self_attn) "
                         f"in it; pass a ReCamMaster checkpoint")
    own = model.state_dict()
    for name, value in mapped.items():
        if name not in own or own[name].shape != value.shape:
            have = tuple(own[name].shape) if name in own else "no such parameter"
            raise ValueError(f"{where}: {name} {tuple(value.shape)} does not fit this transformer ({have}); "
                             f"the checkpoint was trained on another Wan size")
    model.load_state_dict(mapped, strict=False)
    return len(mapped)
