"""Teacher-forced condition gains of the GAIA-2 latent world model: how much each condition lowers the flow-matching
loss of real held-out futures (docs/latent_world_model_notes.md, "What the model reads from its actions").

Legend: b windows, v cameras, t latent steps, C channels, h w latent grid.

Rollout tables score one sampled future per scene and command, so their action rows carry the whole spread of the
sampler. Here nothing is sampled: each window's first `context` steps are clean, the rest noised at fixed flow times
with fixed noise, and the network's velocity error on the noised steps is compared between variants of the window's
conditions (the window's own actions, another window's actions, actions dropped, agents dropped …). The loss a
variant saves over the unconditioned one is what the model reads from that condition; true against swapped actions
is what it reads from *these* actions (the GAIA-1 table's "command discrimination", for a flow model).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import torch

from gaia_app.data.latent_cache import find_latent_clips, read_latent_clip
from gaia_app.data.latent_windows import collate_latent_windows, latent_window
from gaia_app.data.metadata import MetadataEncoder
from gaia_app.diffusion.flow_matching import velocity_target
from gaia_app.eval.intervals import mean_interval
from gaia_app.models.gaia2.conditioning import WorldConditions, batch_conditions
from gaia_app.models.gaia2.latent_world_model import LatentWorldModel


def swapped_actions(cond: WorldConditions) -> WorldConditions:
    """The conditions with each window's actions replaced by those of the window half the batch away (b ≥ 2): in a
    clip-major batch (`every_window`) that is another clip, not the same clip one step later."""
    if cond.actions is None or cond.actions.shape[0] < 2:
        raise ValueError("swapping actions needs at least two windows with actions")
    return replace(cond, actions=torch.roll(cond.actions, cond.actions.shape[0] // 2, dims=0))


def action_variants(cond: WorldConditions) -> dict[str, WorldConditions]:
    """The variants the diagnostic compares: actions true / swapped / dropped, with and without agents."""
    swapped = swapped_actions(cond)
    return {"actions and agents": cond, "swapped actions and agents": swapped, "agents only": cond.without("action"),
            "actions only": cond.without("agents"), "swapped actions only": swapped.without("agents"),
            "neither": cond.without("action", "agents")}


@torch.no_grad()
def flow_losses(net: LatentWorldModel, x: torch.Tensor, variants: Mapping[str, WorldConditions], context: int,
                taus: Sequence[float] = (0.25, 0.5, 0.75), draws: int = 2, seed: int = 0) -> dict[str, torch.Tensor]:
    """Per window (b,) velocity MSE on steps context … t − 1 of latents x (b, v, t, C, h, w) under each variant,
    averaged over the flow times `taus` and `draws` noise draws per time (the same noise for every variant)."""
    b, t = x.shape[0], x.shape[2]
    if not 0 < context < t:
        raise ValueError(f"context must leave generated steps: 0 < context < t = {t}, got {context}")
    generator = torch.Generator(device=x.device).manual_seed(seed)
    totals = {name: torch.zeros(b, device=x.device) for name in variants}
    for tau in taus:
        for _ in range(draws):
            noise = torch.randn(x.shape, generator=generator, device=x.device, dtype=x.dtype)
            times = torch.full((b, t), float(tau), device=x.device)
            times[:, :context] = 1.0
            step = times[:, None, :, None, None, None].to(x.dtype)
            noisy = step * x + (1 - step) * noise
            target = velocity_target(x, noise)
            for name, cond in variants.items():
                error = (net(noisy, times, cond) - target)[:, :, context:].pow(2)
                totals[name] += error.mean(dim=(1, 2, 3, 4, 5))
    return {name: total / (len(taus) * draws) for name, total in totals.items()}


def every_window(folder: str | Path, steps: int, fields: Sequence[str]) -> dict[str, Any]:
    """One batch of every `steps`-step window at every start of every clip of a latent cache split `folder`."""
    encoder = MetadataEncoder(list(fields))
    clips = [read_latent_clip(path) for path in find_latent_clips(folder)]  # none: a ClipError naming the folder
    return collate_latent_windows([latent_window(clip, start, steps, encoder) for clip in clips
                                   for start in range(clip.mean.shape[1] - steps + 1)])


def condition_gain_report(net: LatentWorldModel, batch: dict[str, Any], latent_scale: float, context: int
                          ) -> dict[str, Any]:
    """Losses of `action_variants` on a latent-window batch, what each saves over "neither", and the action
    discrimination (swapped minus own actions, with and without agents); ± 95 % intervals over windows."""
    x = batch["mean"] * latent_scale
    losses = flow_losses(net, x, action_variants(batch_conditions(batch)), context)
    report: dict[str, Any] = {"windows": int(x.shape[0]), "context": context, "losses": {}, "gain_over_neither": {},
                              "action_discrimination": {}}
    for name, loss in losses.items():
        report["losses"][name] = float(loss.mean())
        report["gain_over_neither"][name] = asdict(mean_interval((losses["neither"] - loss).tolist()))
    for agents, (own, other) in {"with agents": ("actions and agents", "swapped actions and agents"),
                                 "without agents": ("actions only", "swapped actions only")}.items():
        report["action_discrimination"][agents] = asdict(mean_interval((losses[other] - losses[own]).tolist()))
    return report
