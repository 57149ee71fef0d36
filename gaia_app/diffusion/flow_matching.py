"""Flow matching on the straight path from noise to data, and its ODE samplers (GAIA-2 report, world model).

Legend: b batch, `...` any trailing dims of a sample (latents `v t c h w`, a 2-D point, …), N solver steps.

Convention of the GAIA-2 report: τ = 0 is pure noise, τ = 1 is data,
    x_τ = τ·x + (1 − τ)·ε,   ε ~ N(0, I),
and the network predicts the velocity v = dx_τ/dτ = x − ε. Sampling integrates dx/dτ = v(x, τ) from
τ = 0 to 1 with an ODE solver (Euler by default, Heun as an option) over a τ grid: the report uses 50
steps of a linear-quadratic schedule (Movie Gen's: small, evenly spaced steps while the sample is
mostly noise, then quadratically growing ones).

Samplers keep no state: a `Velocity` is (x_τ (b, ...), τ (b,)) → v (b, ...), with the network and its
conditioning (and guidance) bound.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tqdm.auto import tqdm

from gaia_app.utils import threads

Velocity = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def expand_like(tau: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """τ (b,) → (b, 1, …, 1) broadcastable against x (b, ...)."""
    return tau.reshape(-1, *([1] * (x.ndim - 1))).to(x.dtype)


def noisy_sample(x: torch.Tensor, noise: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
    """x_τ = τ·x + (1 − τ)·ε for data x and noise ε (b, ...), τ (b,) in [0, 1]."""
    t = expand_like(tau, x)
    return t * x + (1 - t) * noise


def velocity_target(x: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
    """v = x − ε, the constant velocity of the straight path."""
    return x - noise


def sample_tau(n: int, distribution: str = "logit_normal", mean: float = 0.0, std: float = 1.0,
               generator: torch.Generator | None = None, device: torch.device | str | None = None) -> torch.Tensor:
    """Training times τ (n,) in (0, 1).

    distribution: "uniform", or "logit_normal" (τ = sigmoid(N(mean, std)); SD3's choice, weighting the
    middle of the path where the velocity is hardest to predict). The report does not say which.
    """
    if distribution == "uniform":
        return torch.rand(n, generator=generator, device=device)
    if distribution == "logit_normal":
        return torch.sigmoid(mean + std * torch.randn(n, generator=generator, device=device))
    raise ValueError(f"tau distribution {distribution!r}: expected 'uniform' or 'logit_normal'")


def linear_quadratic_taus(steps: int = 50, threshold: float = 0.025, linear_steps: int | None = None) -> torch.Tensor:
    """τ grid (steps + 1,) from 0 (noise) to 1 (data), linear then quadratic (Movie Gen's schedule).

    The first `linear_steps` (default steps // 2) steps advance evenly from τ = 0 to τ = threshold; the
    rest follow a parabola that continues with the same slope and ends exactly at τ = 1. Small steps
    while the sample is mostly noise, where the velocity changes fastest, and large ones near the data.
    """
    linear = steps // 2 if linear_steps is None else linear_steps
    quadratic = steps - linear
    if not 0 < linear < steps or not 0 < threshold < 1:
        raise ValueError(f"linear_quadratic_taus: need 0 < linear_steps < steps and 0 < threshold < 1, got "
                         f"steps={steps}, linear_steps={linear}, threshold={threshold}")
    slope = threshold / linear
    curvature = (1 - threshold - slope * quadratic) / quadratic**2
    if curvature < 0:
        raise ValueError(f"linear_quadratic_taus: threshold={threshold} over {linear} linear steps is too steep to "
                         f"reach τ = 1 with growing steps in {quadratic}; lower the threshold")
    head = torch.arange(linear, dtype=torch.float64) * slope
    k = torch.arange(quadratic + 1, dtype=torch.float64)
    tail = threshold + slope * k + curvature * k**2
    taus = torch.cat([head, tail])
    taus[-1] = 1.0
    return taus.float()


def uniform_taus(steps: int) -> torch.Tensor:
    """Evenly spaced τ grid (steps + 1,) from 0 to 1."""
    return torch.linspace(0.0, 1.0, steps + 1)


class FlowSampler:
    """Integrates dx/dτ = v(x, τ) from noise (τ = taus[0]) to data (τ = 1) over a τ grid.

    Args:
        steps: solver steps N (the report: 50).
        schedule: "linear_quadratic" (the report) or "uniform".
        solver: "euler" (one velocity per step) or "heun" (two: Euler predictor, trapezoidal corrector;
            the last step is plain Euler, as in EDM).
        threshold: τ reached by the linear part of the linear-quadratic schedule.
        progress: show a progress bar.
    """

    def __init__(self, steps: int = 50, schedule: str = "linear_quadratic", solver: str = "euler",
                 threshold: float = 0.025, progress: bool = False):
        if solver not in ("euler", "heun"):
            raise ValueError(f"sampler.solver={solver!r}: expected 'euler' or 'heun'")
        if schedule not in ("linear_quadratic", "uniform"):
            raise ValueError(f"sampler.schedule={schedule!r}: expected 'linear_quadratic' or 'uniform'")
        self.steps, self.schedule, self.solver = steps, schedule, solver
        self.threshold, self.progress = threshold, progress

    def taus(self) -> torch.Tensor:
        """The τ grid (steps + 1,)."""
        if self.schedule == "uniform":
            return uniform_taus(self.steps)
        return linear_quadratic_taus(self.steps, self.threshold)

    def evaluations(self) -> int:
        """Velocity evaluations per sample: N (Euler) or 2N − 1 (Heun)."""
        return self.steps if self.solver == "euler" else 2 * self.steps - 1

    @torch.no_grad()
    def __call__(self, velocity: Velocity, noise: torch.Tensor, start: int = 0) -> torch.Tensor:
        """Integrate from `noise` (b, ...) at τ = taus[start] to τ = 1. A `start` > 0 continues from a
        partially noised sample (scene editing: x = τ·x_real + (1 − τ)·ε at τ = taus[start])."""
        taus = self.taus().to(noise.device)
        x = noise
        b = noise.shape[0]
        for i in tqdm(range(start, self.steps), desc="flow", disable=not self.progress, leave=False):
            threads.tick()  # follow the load other processes put on the CPUs (gaia_app/utils/threads.py)
            t0, t1 = taus[i].expand(b), taus[i + 1].expand(b)
            dt = float(taus[i + 1] - taus[i])
            v0 = velocity(x, t0)
            if self.solver == "heun" and i < self.steps - 1:
                predicted = x + dt * v0
                x = x + dt * 0.5 * (v0 + velocity(predicted, t1))
            else:
                x = x + dt * v0
        return x
