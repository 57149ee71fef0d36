"""Training of the GAIA-2 latent world model by flow matching (GAIA-2 report, world model).

Batch: `collate_latent_windows` of a latent cache ("mean"/"logvar": (b, v, t, C, h, w), "timestamps": (b, t),
"actions"?: (b, t, 2), "intrinsics"/"extrinsics": (b, v, 3, 3)/(b, v, 4, 4), "agents_*"?, "metadata", "text"?).

Each sample is a task drawn per batch element (the report mixes "from scratch" generation and context
prediction): with probability `context_prob` its first k ∈ [1, t − 1] latent steps are clean context
(τ = 1) and the rest are noised at one τ; otherwise every step is noised at one τ. The loss is the mean
squared error of the velocity x − ε on the noised steps only. Latents are drawn from the tokenizer's
posterior (`sample_posterior`) and scaled by `latent_scale` to about unit variance.

Optionally (`agent_loss_weight` λ > 0, not in the report) the training loss weighs each latent position 1 + λ·(the
share of its cell the agents' projected boxes cover), scaled to mean 1, as the road-users tokenizer weighs its pixels
(docs/tokenizer.md): agents cover a few percent of the grid, so unweighted they give the net little reason to read
its agent tokens. Validation stays unweighted, so its loss compares across runs.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from einops import rearrange
from torch import nn

from gaia_app.diffusion.flow_matching import sample_tau, velocity_target
from gaia_app.lit.captioned import CaptionedModule
from gaia_app.models.gaia2.conditioning import (
    WorldConditions,
    batch_conditions,
    batch_text_vector,
    cell_coverage,
    project_boxes,
)
from gaia_app.models.gaia2.latent_world_model import LatentWorldModel
from gaia_app.nn.distributions import DiagonalGaussian


class LatentWorldModelModule(CaptionedModule):
    """Flow-matching objective of the latent world model.

    Args:
        net, optim, sched: see GaiaModule.
        text_encoder: frozen caption encoder (b, t, m, e) factory, or None; its tokens are mean-pooled into
            the model's text vector (the report uses CLIP embeddings; MiniLM by default here).
        tau_distribution, tau_mean, tau_std: training τ sampling (flow_matching.sample_tau).
        context_prob: share of samples trained as context prediction (the rest: from scratch).
        sample_posterior: draw latents from the posterior (True) or use its mean.
        latent_scale: latents are multiplied by it (about 1 / their standard deviation).
        val_taus: fixed τ values at which validation measures the loss (comparable across runs).
        init_from: a latent world model checkpoint, or a weights folder (e.g. "gaia2", the shipped one), whose net
            weights (and a trainable text encoder's) start a fresh fit (fine-tuning, e.g. on a real rig after
            synthetic pre-training: the net takes any number of cameras); None: random init.
        agent_loss_weight: λ of the agent-weighted training loss (`position_weights`); 0: the report's plain mean.
    """

    component = "latent_world_model"
    net_prefixes = {"net": "net.", "text_encoder": "text_encoder."}
    init_from_what = "a latent world model checkpoint of the same preset (and model/text_encoder)"

    def __init__(self, net: Callable[[], LatentWorldModel], optim: Callable, sched: Callable | None = None,
                 text_encoder: Callable[[], nn.Module] | None = None, tau_distribution: str = "logit_normal",
                 tau_mean: float = 0.0, tau_std: float = 1.0, context_prob: float = 0.5, sample_posterior: bool = True,
                 latent_scale: float = 1.0, val_taus: tuple[float, ...] = (0.25, 0.5, 0.75),
                 init_from: str | None = None, agent_loss_weight: float = 0.0):
        super().__init__(net, optim, sched, text_encoder, init_from)
        if agent_loss_weight < 0:
            raise ValueError(f"model.agent_loss_weight must be ≥ 0 (0: unweighted), got {agent_loss_weight}")
        self.agent_loss_weight = float(agent_loss_weight)
        self.tau_distribution, self.tau_mean, self.tau_std = tau_distribution, tau_mean, tau_std
        self.context_prob, self.sample_posterior, self.latent_scale = context_prob, sample_posterior, latent_scale
        self.val_taus = tuple(val_taus)

    @property
    def model(self) -> LatentWorldModel:
        self.configure_model()
        return self.net  # type: ignore[return-value]

    def latents(self, batch: dict[str, Any], sample: bool) -> torch.Tensor:
        """(b, v, t, C, h, w) scaled latents: a posterior sample or the mean."""
        posterior = DiagonalGaussian(batch["mean"], batch["logvar"])
        return (posterior.sample() if sample else posterior.mode()) * self.latent_scale

    def text_vector(self, batch: dict[str, Any]) -> torch.Tensor | None:
        """(b, e) mean of the caption's token features, or None without captions or text encoder."""
        return batch_text_vector(self.text_encoder, batch)

    def task_taus(self, b: int, t: int, tau: torch.Tensor, context: torch.Tensor | None = None) -> torch.Tensor:
        """(b, t) flow times: τ per sample on its generated steps, 1 on its `context` (b,) clean first steps."""
        taus = tau[:, None].expand(b, t).clone()
        if context is not None:
            taus[torch.arange(t, device=tau.device)[None, :] < context[:, None]] = 1.0
        return taus

    def draw_context(self, b: int, t: int, device: torch.device) -> torch.Tensor:
        """(b,) clean context steps: 0 (from scratch) or k ∈ [1, t − 1] with probability context_prob."""
        if t < 2:
            return torch.zeros(b, dtype=torch.long, device=device)
        k = torch.randint(1, t, (b,), device=device)
        return torch.where(torch.rand(b, device=device) < self.context_prob, k, torch.zeros_like(k))

    def position_weights(self, x: torch.Tensor, cond: WorldConditions) -> torch.Tensor | None:
        """(b, v, t, 1, h, w) loss weights 1 + λ·min(1, Σ agents' box coverage of the cell) for latents x
        (b, v, t, C, h, w), scaled to mean 1; None when `agent_loss_weight` is 0."""
        if self.agent_loss_weight == 0:
            return None
        if cond.agents is None:
            raise ValueError("model.agent_loss_weight > 0 needs agent boxes in the latent cache (agents_* in "
                             "conditions.json: encode clips that have agents, e.g. data=synthetic_rig)")
        boxes, _, visible = project_boxes(cond.agents, cond.intrinsics, cond.extrinsics, cond.image_size)
        cover = cell_coverage(boxes, tuple(x.shape[-2:])) * visible[..., None, None]  # (b, t, v, N, h, w)
        inside = cover.sum(dim=3).clamp(max=1.0).to(x.dtype)  # (b, t, v, h, w)
        weight = 1 + self.agent_loss_weight * rearrange(inside, "b t v h w -> b v t 1 h w")
        return weight / weight.mean()

    def flow_loss(self, x: torch.Tensor, taus: torch.Tensor, cond: WorldConditions,
                  noise: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
        """Mean squared velocity error over the noised steps (taus < 1) of x (b, v, t, C, h, w); `weights`
        (b, v, t, 1, h, w) weigh each latent position (`position_weights`)."""
        step_tau = taus[:, None, :, None, None, None].to(x.dtype)
        x_tau = step_tau * x + (1 - step_tau) * noise  # flow_matching.noisy_sample per step; τ = 1 leaves x exact
        squared = (self.model(x_tau, taus, cond) - velocity_target(x, noise)).pow(2)
        if weights is not None:
            squared = squared * weights
        error = squared.mean(dim=(1, 3, 4, 5))  # (b, t)
        generated = (taus < 1.0).float()
        return (error * generated).sum() / generated.sum().clamp_min(1.0)

    def training_step(self, batch: dict[str, Any], batch_idx: int) -> torch.Tensor:
        x = self.latents(batch, self.sample_posterior)
        b, t = x.shape[0], x.shape[2]
        tau = sample_tau(b, self.tau_distribution, self.tau_mean, self.tau_std, device=x.device)
        context = self.draw_context(b, t, x.device)
        cond = batch_conditions(batch, self.text_vector(batch))
        loss = self.flow_loss(x, self.task_taus(b, t, tau, context), cond, torch.randn_like(x),
                              self.position_weights(x, cond))
        self.log("train/loss", loss, prog_bar=True, batch_size=b)
        return loss

    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> None:
        x = self.latents(batch, sample=False)
        b, t = x.shape[0], x.shape[2]
        cond = batch_conditions(batch, self.text_vector(batch))
        generator = torch.Generator(device=x.device).manual_seed(batch_idx)
        noise = torch.randn(x.shape, generator=generator, device=x.device, dtype=x.dtype)
        losses = []
        for value in self.val_taus:
            tau = torch.full((b,), value, device=x.device)
            losses.append(self.flow_loss(x, self.task_taus(b, t, tau), cond, noise))
            self.log(f"val/loss_tau{value:g}", losses[-1], batch_size=b)
        self.log("val/loss", torch.stack(losses).mean(), prog_bar=True, batch_size=b)
