"""Random-walk noise on the input state of a training window (GNS, MeshGraphNets): the model starts each window from
a slightly wrong state and is scored against the true frames, so it learns to pull drift back instead of
compounding it over long rollouts.

The state's velocity is the frame-mean velocity v_t = (x_t - x_{t-1}) / Δt, so the noise is a two-step random walk on
positions: x_{t-1} gets n_prev ~ N(0, σ²/2), x_t gets n = n_prev + N(0, σ²/2) (std σ), and v_t gets (n - n_prev) / Δt.
The noisy x and v stay consistent with a noisy previous frame.
"""

from __future__ import annotations

import math

import torch


def noisy_state(x: torch.Tensor, v: torch.Tensor, std_m: float, dt: float) -> tuple[torch.Tensor, torch.Tensor]:
    """x, v (B, N, 3) with random-walk noise of std `std_m` [m] on x (and its difference quotient on v); unchanged for
    std 0. Draws from torch's generator of x's device (graph-safe on CUDA)."""
    if std_m < 0:
        raise ValueError(f"input noise std must be >= 0 m, got {std_m}")
    if std_m == 0:
        return x, v
    half = std_m / math.sqrt(2.0)
    previous = half * torch.randn_like(x)
    step = half * torch.randn_like(x)
    return x + previous + step, v + step / dt


def noisy_history(x: torch.Tensor, std_m: float) -> torch.Tensor:
    """Observed frames x (B, H, N, 3) [m] with a random walk over the H frames whose last frame has noise std `std_m`
    [m] (each frame's step N(0, std²/H)); unchanged for std 0. For models that read past positions (the baselines)."""
    if std_m < 0:
        raise ValueError(f"input noise std must be >= 0 m, got {std_m}")
    if std_m == 0:
        return x
    steps = std_m / math.sqrt(x.shape[1]) * torch.randn_like(x)
    return x + steps.cumsum(1)
