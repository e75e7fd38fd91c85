"""A compact video DiT with ReCamDriving's two-stage conditioning.

Stage 1 (relative-pose control): the camera encoder maps the relative pose ΔT (target <- source)
to ``c_r`` and the identity pose to ``c_I``; with a learnable frame embedding ``E_f`` the DiT reads

    x_i = Cat_frames(x_t + c_r + E_f,  x_s + c_I + E_f)          (B, 2f, l, d)

and predicts the velocity of the first half (the noisy target tokens).

Stage 2 (3DGS guidance): every block gains a *Rendering Attention* (self-attention over the
condition-rendering tokens ``x_gs + c_r + E_f``, carried from block to block as a second stream)
and a *Cross Attention* from the diffusion tokens (after the block's self-attention) to them.
Stage-1 parameters are frozen; the cross attention's output projection starts at zero so a fresh
stage-2 model computes exactly what its stage-1 weights did.

Shapes: B batch, f latent frames, c latent channels, h x w latent grid, l = (h/p)(w/p) tokens per
frame, d model width.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

# Parameter-name prefixes (inside each block) of the modules stage 2 adds.
STAGE2_MODULES = ("render_norm", "render_attn", "cross_norm", "cross_attn")


@dataclass
class ModelConfig:
    latent_channels: int
    dim: int = 256
    depth: int = 8
    heads: int = 4
    mlp_ratio: float = 4.0
    patch: int = 1
    max_frames: int = 64
    rendering: bool = False

    def to_dict(self) -> dict:
        return asdict(self)


def timestep_embedding(t: torch.Tensor, dim: int, max_period: float = 10000.0) -> torch.Tensor:
    """Sinusoidal embedding of flow times t in [0, 1]: (B,) -> (B, dim). Scaled by 1000 so the
    frequencies span the range DiT's were designed for (integer diffusion steps)."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
    args = (t.float() * 1000.0)[:, None] * freqs[None]
    return torch.cat([torch.cos(args), torch.sin(args)], dim=-1)


def sincos_2d(h: int, w: int, dim: int, device=None) -> torch.Tensor:
    """Fixed 2-D sine-cosine position embedding of an h x w token grid: (h*w, dim)."""
    quarter = dim // 4
    omega = 1.0 / 10000 ** (torch.arange(quarter, dtype=torch.float32, device=device) / quarter)
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float32, device=device),
                            torch.arange(w, dtype=torch.float32, device=device), indexing="ij")
    out = []
    for coord in (ys.flatten(), xs.flatten()):
        a = coord[:, None] * omega[None]
        out += [torch.sin(a), torch.cos(a)]
    emb = torch.cat(out, dim=-1)
    return F.pad(emb, (0, dim - emb.shape[-1]))


class Attention(nn.Module):
    """Multi-head attention with RMS-normalised queries and keys (as in Wan's DiT).

    Self-attention when ``context`` is None, else cross-attention from ``x`` to ``context``.
    x (B, N, d), context (B, M, d) -> (B, N, d).
    """

    def __init__(self, dim: int, heads: int, zero_out: bool = False):
        super().__init__()
        if dim % heads:
            raise ValueError(f"model dim {dim} is not divisible by heads {heads}")
        self.heads = heads
        self.q = nn.Linear(dim, dim)
        self.kv = nn.Linear(dim, 2 * dim)
        self.q_norm = nn.RMSNorm(dim // heads, eps=1e-6)
        self.k_norm = nn.RMSNorm(dim // heads, eps=1e-6)
        self.out = nn.Linear(dim, dim)
        if zero_out:
            nn.init.zeros_(self.out.weight)
            nn.init.zeros_(self.out.bias)

    def forward(self, x: torch.Tensor, context: torch.Tensor | None = None) -> torch.Tensor:
        b, n, d = x.shape
        context = x if context is None else context
        q = self.q(x).view(b, n, self.heads, -1)
        k, v = self.kv(context).view(b, context.shape[1], 2, self.heads, -1).unbind(2)
        q, k, v = self.q_norm(q).transpose(1, 2), self.k_norm(k).transpose(1, 2), v.transpose(1, 2)
        y = F.scaled_dot_product_attention(q, k, v)
        return self.out(y.transpose(1, 2).reshape(b, n, d))


def _modulate(x: torch.Tensor, shift: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    return x * (1 + scale) + shift


class DiTBlock(nn.Module):
    """Self-attention + FFN with adaLN-Zero time modulation; with ``rendering``, also the stage-2
    Rendering Attention (on the condition stream) and Cross Attention (diffusion -> condition)."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float, rendering: bool):
        super().__init__()
        self.modulation = nn.Linear(dim, 6 * dim)
        nn.init.zeros_(self.modulation.weight)
        nn.init.zeros_(self.modulation.bias)
        self.norm1 = nn.LayerNorm(dim, elementwise_affine=False, eps=1e-6)
        self.self_attn = Attention(dim, heads)
        self.norm2 = nn.LayerNorm(dim, elementwise_affine=False, eps=1e-6)
        hidden = int(dim * mlp_ratio)
        self.ffn = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(approximate="tanh"), nn.Linear(hidden, dim))
        self.rendering = rendering
        if rendering:
            self.render_norm = nn.LayerNorm(dim, eps=1e-6)
            self.render_attn = Attention(dim, heads)
            self.cross_norm = nn.LayerNorm(dim, eps=1e-6)
            self.cross_attn = Attention(dim, heads, zero_out=True)

    def forward(self, x: torch.Tensor, temb: torch.Tensor,
                cond: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
        """x (B, N, d) diffusion tokens, temb (B, d), cond (B, M, d) condition tokens or None."""
        shift1, scale1, gate1, shift2, scale2, gate2 = self.modulation(F.silu(temb))[:, None].chunk(6, dim=-1)
        x = x + gate1 * self.self_attn(_modulate(self.norm1(x), shift1, scale1))
        if self.rendering and cond is not None:
            cond = cond + self.render_attn(self.render_norm(cond))
            x = x + self.cross_attn(self.cross_norm(x), cond)
        x = x + gate2 * self.ffn(_modulate(self.norm2(x), shift2, scale2))
        return x, cond


class CameraEncoder(nn.Module):
    """E_cam: a camera pose (its 3x4 upper part, 12 numbers) -> a d-vector per latent frame.
    pose (B, f, 4, 4) -> (B, f, d)."""

    def __init__(self, dim: int):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(12, dim), nn.SiLU(), nn.Linear(dim, dim))

    def forward(self, pose: torch.Tensor) -> torch.Tensor:
        return self.net(pose[..., :3, :4].flatten(-2).to(next(self.net.parameters()).dtype))


class VideoDiT(nn.Module):
    """The ReCamDriving denoiser: predicts the velocity of the target latents.

    forward(x_t, t, x_s, rel_pose, identity_pose=None, condition=None) -> (B, f, c, h, w)
      x_t        (B, f, c, h, w)  noisy target latents at flow time t
      t          (B,)             flow time in [0, 1] (0 = noise, 1 = data)
      x_s        (B, f, c, h, w)  source-video latents
      rel_pose   (B, f, 4, 4)     ΔT per latent frame, target <- source
      identity_pose (B, f, 4, 4)  the identity (zero motion); made here when None
      condition  (B, f, c, h, w)  3DGS condition-rendering latents (stage 2 only)
    """

    def __init__(self, config: ModelConfig):
        super().__init__()
        self.config = config
        d, p = config.dim, config.patch
        self.patch_embed = nn.Linear(config.latent_channels * p * p, d)
        self.camera_encoder = CameraEncoder(d)
        self.frame_embed = nn.Parameter(torch.randn(config.max_frames, d) * 0.02)
        self.time_embed = nn.Sequential(nn.Linear(256, d), nn.SiLU(), nn.Linear(d, d))
        self.blocks = nn.ModuleList(DiTBlock(d, config.heads, config.mlp_ratio, config.rendering)
                                    for _ in range(config.depth))
        self.head_norm = nn.LayerNorm(d, elementwise_affine=False, eps=1e-6)
        self.head_modulation = nn.Linear(d, 2 * d)
        self.head = nn.Linear(d, config.latent_channels * p * p)
        for layer in (self.head_modulation, self.head):
            nn.init.zeros_(layer.weight)
            nn.init.zeros_(layer.bias)

    # -- tokens ---------------------------------------------------------------------------------
    def patchify(self, x: torch.Tensor) -> torch.Tensor:
        """latents (B, f, c, h, w) -> patch tokens with 2-D positions (B, f, l, d)."""
        b, f, c, h, w = x.shape
        p = self.config.patch
        if h % p or w % p:
            raise ValueError(f"latent grid {h}x{w} does not divide into model.patch={p}")
        x = x.reshape(b, f, c, h // p, p, w // p, p).permute(0, 1, 3, 5, 2, 4, 6)
        x = x.reshape(b, f, (h // p) * (w // p), c * p * p)
        return self.patch_embed(x) + sincos_2d(h // p, w // p, self.config.dim, x.device).to(x.dtype)

    def unpatchify(self, tokens: torch.Tensor, h: int, w: int) -> torch.Tensor:
        """(B, f, l, c*p*p) -> (B, f, c, h, w)."""
        b, f, _, _ = tokens.shape
        p, c = self.config.patch, self.config.latent_channels
        x = tokens.reshape(b, f, h // p, w // p, c, p, p).permute(0, 1, 4, 2, 5, 3, 6)
        return x.reshape(b, f, c, h, w)

    def frame_embedding(self, frames: int) -> torch.Tensor:
        """E_f for ``frames`` latent frames: (f, d)."""
        if frames > self.config.max_frames:
            raise ValueError(f"{frames} latent frames exceed model.max_frames={self.config.max_frames}")
        return self.frame_embed[:frames]

    def embed_inputs(self, x_t: torch.Tensor, x_s: torch.Tensor, rel_pose: torch.Tensor,
                     identity_pose: torch.Tensor | None = None) -> torch.Tensor:
        """x_i = Cat_frames(x_t + c_r + E_f, x_s + c_I + E_f): (B, 2f, l, d).

        c_r = E_cam(ΔT) and c_I = E_cam(I) are per frame, broadcast over the l tokens of a frame.
        """
        f = x_t.shape[1]
        if identity_pose is None:
            identity_pose = torch.eye(4, dtype=rel_pose.dtype, device=rel_pose.device).expand_as(rel_pose)
        e_f = self.frame_embedding(f)[None, :, None]
        c_r = self.camera_encoder(rel_pose)[:, :, None]
        c_i = self.camera_encoder(identity_pose)[:, :, None]
        return torch.cat([self.patchify(x_t) + c_r + e_f, self.patchify(x_s) + c_i + e_f], dim=1)

    def embed_condition(self, condition: torch.Tensor, rel_pose: torch.Tensor) -> torch.Tensor:
        """x̄_gs = x_gs + c_r + E_f: (B, f, l, d). Shares the patch embedding, camera encoder and
        frame embedding with stage 1 (the paper encodes renderings with the same VAE and patchify)."""
        f = condition.shape[1]
        return (self.patchify(condition) + self.camera_encoder(rel_pose)[:, :, None]
                + self.frame_embedding(f)[None, :, None])

    # -- forward --------------------------------------------------------------------------------
    def forward(self, x_t: torch.Tensor, t: torch.Tensor, x_s: torch.Tensor, rel_pose: torch.Tensor,
                identity_pose: torch.Tensor | None = None,
                condition: torch.Tensor | None = None) -> torch.Tensor:
        b, f, c, h, w = x_t.shape
        if x_s.shape != x_t.shape:
            raise ValueError(f"source latents {tuple(x_s.shape)} and target latents {tuple(x_t.shape)} differ")
        if rel_pose.shape[:2] != (b, f):
            raise ValueError(f"rel_pose {tuple(rel_pose.shape)} needs one pose per latent frame ({b}, {f}, 4, 4)")
        if self.config.rendering and condition is None:
            raise ValueError("this is a stage-2 model: pass the condition-rendering latents")
        seq = self.embed_inputs(x_t, x_s, rel_pose, identity_pose)
        l = seq.shape[2]
        x = seq.flatten(1, 2)
        cond = None
        if self.config.rendering:
            assert condition is not None, "a rendering model needs the condition video"
            cond = self.embed_condition(condition, rel_pose).flatten(1, 2)
        temb = self.time_embed(timestep_embedding(t.expand(b) if t.ndim == 0 else t, 256).to(x.dtype))
        for block in self.blocks:
            x, cond = block(x, temb, cond)
        shift, scale = self.head_modulation(F.silu(temb))[:, None].chunk(2, dim=-1)
        out = self.head(_modulate(self.head_norm(x), shift, scale))
        target_half = out.view(b, 2 * f, l, -1)[:, :f]
        return self.unpatchify(target_half, h, w)


def is_stage2_parameter(name: str) -> bool:
    """True for parameters of the modules stage 2 adds (Rendering / Cross Attention and their norms)."""
    return any(f".{m}." in f".{name}" for m in STAGE2_MODULES)


def load_stage1_weights(model: VideoDiT, state_dict: dict) -> None:
    """Load stage-1 weights into a (stage-2) model; only the stage-2 modules may be missing."""
    result = model.load_state_dict(state_dict, strict=False)
    missing = [k for k in result.missing_keys if not is_stage2_parameter(k)]
    if missing or result.unexpected_keys:
        raise ValueError(f"stage-1 weights do not fit this model: missing {missing[:5]}, "
                         f"unexpected {result.unexpected_keys[:5]}; check model.dim/depth/heads/patch "
                         f"and the autoencoder match the stage-1 run")
