"""Rectified flow: the training loss, its time schedules and weightings, and an Euler ODE sampler.

Convention of the paper (§3.1): t = 0 is noise x0 ~ N(0, I), t = 1 is data x1,
x_t = t·x1 + (1 − t)·x0, and the network predicts the velocity v = x1 − x0. Wan, DiffSynth-Studio
and ReCamMaster write the same path with σ = 1 − t (``(1 − σ)·x + σ·noise``, timestep 1000·σ).

Noise and times are drawn either from one generator for the whole batch or from one generator per
sample: with one per sample, a sample's draw does not depend on which batch, micro-batch or process
it lands in, so a run computes the same on any number of processes.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch

# velocity(x_t (B, ...), t (B,)) -> (B, ...)
Velocity = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
Generators = torch.Generator | Sequence[torch.Generator] | None

SCHEDULES = ("uniform", "logit_normal")
WEIGHTINGS = ("none", "recammaster")
# DiffSynth-Studio's training grid (``set_timesteps(1000, training=True)``): 1000 values of σ on
# Wan's 1000-step timestep axis
GRID_STEPS = 1000
TRAIN_TIMESTEPS = 1000


def shift_times(t: torch.Tensor, shift: float) -> torch.Tensor:
    """t' = t / (t + shift·(1 − t)): ``shift`` > 1 moves times toward the noise end (σ' = shift·σ /
    (1 + (shift − 1)·σ) with σ = 1 − t, Wan's and SD3's shift)."""
    return t if shift == 1.0 else t / (t + shift * (1 - t))


def recammaster_grid(shift: float, steps: int = GRID_STEPS) -> tuple[torch.Tensor, torch.Tensor]:
    """ReCamMaster's (DiffSynth-Studio's) training times and their loss weights, float64 (steps,).

    σ_k = 1 − k/steps for k = 0 .. steps − 1 (σ = 1 down to 1/steps; the 0 end left out), shifted
    (:func:`shift_times`), timestep τ_k = 1000·σ_k; the weight is the bell
    y_k = exp(−2·((τ_k − steps/2) / steps)²) less its minimum, scaled to average 1 over the grid.
    Returned as flow times t_k = 1 − σ_k and weights w_k.
    """
    k = torch.arange(steps, dtype=torch.float64, device="cpu")
    t = shift_times(k / steps, shift)
    timestep = (1.0 - t) * TRAIN_TIMESTEPS
    bell = torch.exp(-2.0 * ((timestep - steps / 2) / steps) ** 2)
    bell = bell - bell.min()
    return t, bell * (steps / bell.sum())


def _one_draw(shape: Sequence[int], generator: torch.Generator | None, schedule: str,
              weighting: str, shift: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Noise ``shape``, times (n,) and weights (n,) from one generator, noise first."""
    n = shape[0]
    x0 = torch.randn(tuple(shape), generator=generator, device="cpu")
    if weighting == "recammaster":
        grid, weights = recammaster_grid(shift)
        index = torch.randint(0, GRID_STEPS, (n,), generator=generator, device="cpu")
        return x0, grid[index].float(), weights[index].float()
    return x0, sample_times(n, generator, schedule, shift), torch.ones(n, device="cpu")


def draw(shape: Sequence[int], generator: Generators = None, schedule: str = "uniform", shift: float = 1.0,
         weighting: str = "none") -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Noise x0 ``shape`` (B, ...), times t (B,) in (0, 1) and loss weights (B,), on the CPU.

    ``schedule`` (``weighting="none"``): ``uniform`` t ~ U(0, 1), the paper's objective, or
    ``logit_normal`` t = sigmoid(N(0, 1)) (SD3), then shifted; weights 1. ``weighting="recammaster"``:
    t uniform over :func:`recammaster_grid` (shifted by ``shift``) with its bell weight, as
    ReCamMaster trains (``schedule`` is not used). ``generator``: one for the batch, or one per
    sample (a sequence of B).
    """
    if weighting not in WEIGHTINGS:
        raise ValueError(f"flow.weighting={weighting!r}: use one of {', '.join(WEIGHTINGS)}")
    if generator is None or isinstance(generator, torch.Generator):
        return _one_draw(shape, generator, schedule, weighting, shift)
    if len(generator) != shape[0]:
        raise ValueError(f"{len(generator)} generators for a batch of {shape[0]}")
    parts = [_one_draw((1, *shape[1:]), g, schedule, weighting, shift) for g in generator]
    x0, t, w = (torch.cat(p) for p in zip(*parts))
    return x0, t, w


def sample_times(batch: int, generator: torch.Generator | None = None, schedule: str = "uniform",
                 shift: float = 1.0, device=None) -> torch.Tensor:
    """Training times t in (0, 1): (B,) of ``schedule``, shifted (see :func:`draw`)."""
    if schedule == "uniform":
        t = torch.rand(batch, generator=generator, device="cpu")
    elif schedule == "logit_normal":
        t = torch.sigmoid(torch.randn(batch, generator=generator, device="cpu"))
    else:
        raise ValueError(f"flow.schedule={schedule!r}: use one of {', '.join(SCHEDULES)}")
    return shift_times(t, shift).to(device)


def interpolate(x0: torch.Tensor, x1: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """x_t = t·x1 + (1 − t)·x0 with t (B,) broadcast over the other dimensions."""
    t = t.view(-1, *([1] * (x1.dim() - 1))).to(x1.dtype)
    return t * x1 + (1 - t) * x0


def flow_matching_loss(velocity: Velocity, x1: torch.Tensor, generator: Generators = None,
                       schedule: str = "uniform", shift: float = 1.0, weighting: str = "none") -> torch.Tensor:
    """L_FM = mean over the batch of w_i · mean ||v_θ(x_t, t) − (x1 − x0)||² on the target latents
    x1 (B, ...), noise, times and weights from :func:`draw` (w = 1 unless ``weighting``).

    ``velocity`` sees only x_t and t; the caller binds the conditions (source latents, ΔT,
    condition rendering). Noise and times come from ``generator`` so a run is reproducible.
    """
    x0, t, w = draw(x1.shape, generator, schedule, shift, weighting)
    x0, t, w = x0.to(x1.device, x1.dtype), t.to(x1.device), w.to(x1.device)
    prediction = velocity(interpolate(x0, x1, t), t)
    per_sample = (prediction.float() - (x1 - x0).float()).square().flatten(1).mean(1)
    return (per_sample * w).mean()


@torch.no_grad()
def euler_sample(velocity: Velocity, noise: torch.Tensor, steps: int, shift: float = 1.0) -> torch.Tensor:
    """Integrate dx/dt = v(x, t) from t = 0 (``noise``) to t = 1 in ``steps`` Euler steps.

    noise (B, ...) -> data estimate, same shape. ``shift`` spaces the steps as in training.
    """
    if steps < 1:
        raise ValueError(f"sampling needs at least one step, got {steps}")
    ts = shift_times(torch.linspace(0.0, 1.0, steps + 1, dtype=torch.float64, device="cpu"), shift)
    x = noise
    for t0, t1 in zip(ts[:-1].tolist(), ts[1:].tolist()):
        t = torch.full((x.shape[0],), t0, dtype=torch.float32, device=x.device)
        x = x + (t1 - t0) * velocity(x, t)
    return x
