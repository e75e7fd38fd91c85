"""Rectified flow: the training loss and an Euler ODE sampler.

Convention of the paper (§3.1): t = 0 is noise x0 ~ N(0, I), t = 1 is data x1,
x_t = t·x1 + (1 − t)·x0, and the network predicts the velocity v = x1 − x0.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F

# velocity(x_t (B, f, c, h, w), t (B,)) -> (B, f, c, h, w)
Velocity = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def sample_times(batch: int, generator: torch.Generator | None = None, schedule: str = "uniform",
                 shift: float = 1.0, device=None) -> torch.Tensor:
    """Training times t in (0, 1): (B,).

    ``uniform``: t ~ U(0, 1), the paper's objective. ``logit_normal``: t = sigmoid(N(0, 1)), which
    weights the middle of the path (SD3). ``shift`` > 1 moves times toward the noise end
    (t' = t / (t + shift·(1 − t))), as Wan and SD3 do at high resolution.
    """
    if schedule == "uniform":
        t = torch.rand(batch, generator=generator)
    elif schedule == "logit_normal":
        t = torch.sigmoid(torch.randn(batch, generator=generator))
    else:
        raise ValueError(f"flow.schedule={schedule!r}: use 'uniform' or 'logit_normal'")
    if shift != 1.0:
        t = t / (t + shift * (1 - t))
    return t.to(device)


def interpolate(x0: torch.Tensor, x1: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """x_t = t·x1 + (1 − t)·x0 with t (B,) broadcast over the other dimensions."""
    t = t.view(-1, *([1] * (x1.dim() - 1))).to(x1.dtype)
    return t * x1 + (1 - t) * x0


def flow_matching_loss(velocity: Velocity, x1: torch.Tensor, generator: torch.Generator | None = None,
                       schedule: str = "uniform", shift: float = 1.0) -> torch.Tensor:
    """L_FM = E ||v_θ(x_t, t) − (x1 − x0)||² on the target latents x1 (B, f, c, h, w).

    ``velocity`` sees only x_t and t; the caller binds the conditions (source latents, ΔT,
    condition rendering). Noise and times come from ``generator`` so a run is reproducible.
    """
    x0 = torch.randn(x1.shape, generator=generator).to(x1.device, x1.dtype)
    t = sample_times(x1.shape[0], generator, schedule, shift, x1.device)
    prediction = velocity(interpolate(x0, x1, t), t)
    return F.mse_loss(prediction.float(), (x1 - x0).float())


@torch.no_grad()
def euler_sample(velocity: Velocity, noise: torch.Tensor, steps: int, shift: float = 1.0) -> torch.Tensor:
    """Integrate dx/dt = v(x, t) from t = 0 (``noise``) to t = 1 in ``steps`` Euler steps.

    noise (B, f, c, h, w) -> data estimate, same shape. ``shift`` spaces the steps as in training.
    """
    if steps < 1:
        raise ValueError(f"sampling needs at least one step, got {steps}")
    ts = torch.linspace(0.0, 1.0, steps + 1, dtype=torch.float64)
    if shift != 1.0:
        ts = ts / (ts + shift * (1 - ts))
    x = noise
    for t0, t1 in zip(ts[:-1].tolist(), ts[1:].tolist()):
        t = torch.full((x.shape[0],), t0, dtype=torch.float32, device=x.device)
        x = x + (t1 - t0) * velocity(x, t)
    return x
