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

ACTION_COMPONENTS = ("speed", "curvature")  # the columns of WorldConditions.actions (b, t, 2)
TAUS = (0.25, 0.5, 0.75)  # the flow times scored (τ = 1 clean, 0 pure noise)


def swapped_actions(cond: WorldConditions, components: Sequence[str] = ACTION_COMPONENTS) -> WorldConditions:
    """The conditions with each window's actions replaced by those of the window half the batch away (b ≥ 2): in a
    clip-major batch (`every_window`) that is another clip, not the same clip one step later. `components` names
    the columns swapped (the others stay the window's own), so speed and curvature can be read apart."""
    if cond.actions is None or cond.actions.shape[0] < 2:
        raise ValueError("swapping actions needs at least two windows with actions")
    unknown = set(components) - set(ACTION_COMPONENTS)
    if unknown or not components:
        raise ValueError(f"action components to swap: expected a non-empty subset of {ACTION_COMPONENTS}, "
                         f"got {list(components)}")
    rolled = torch.roll(cond.actions, cond.actions.shape[0] // 2, dims=0)
    columns = torch.tensor([name in components for name in ACTION_COMPONENTS], device=cond.actions.device)
    return replace(cond, actions=torch.where(columns, rolled, cond.actions))


def action_variants(cond: WorldConditions) -> dict[str, WorldConditions]:
    """The variants the diagnostic compares: actions true / swapped / dropped, with and without agents, and one
    action component swapped at a time (agents given)."""
    swapped = swapped_actions(cond)
    return {"actions and agents": cond, "swapped actions and agents": swapped, "agents only": cond.without("action"),
            "actions only": cond.without("agents"), "swapped actions only": swapped.without("agents"),
            "neither": cond.without("action", "agents"),
            **{f"swapped {name} and agents": swapped_actions(cond, (name,)) for name in ACTION_COMPONENTS}}


@torch.no_grad()
def flow_loss_table(net: LatentWorldModel, x: torch.Tensor, variants: Mapping[str, WorldConditions], context: int,
                    taus: Sequence[float] = TAUS, draws: int = 2, seed: int = 0
                    ) -> dict[str, torch.Tensor]:
    """Per window, flow time and generated step (b, len(taus), t − context): the velocity MSE on steps
    context … t − 1 of latents x (b, v, t, C, h, w) under each variant, averaged over `draws` noise draws per time
    (the same noise for every variant)."""
    b, t = x.shape[0], x.shape[2]
    if not 0 < context < t:
        raise ValueError(f"context must leave generated steps: 0 < context < t = {t}, got {context}")
    generator = torch.Generator(device=x.device).manual_seed(seed)
    tables = {name: torch.zeros(b, len(taus), t - context, device=x.device) for name in variants}
    for i, tau in enumerate(taus):
        for _ in range(draws):
            noise = torch.randn(x.shape, generator=generator, device=x.device, dtype=x.dtype)
            times = torch.full((b, t), float(tau), device=x.device)
            times[:, :context] = 1.0
            step = times[:, None, :, None, None, None].to(x.dtype)
            noisy = step * x + (1 - step) * noise
            target = velocity_target(x, noise)
            for name, cond in variants.items():
                error = (net(noisy, times, cond) - target)[:, :, context:].pow(2)
                tables[name][:, i] += error.mean(dim=(1, 3, 4, 5)) / draws
    return tables


def flow_losses(net: LatentWorldModel, x: torch.Tensor, variants: Mapping[str, WorldConditions], context: int,
                taus: Sequence[float] = TAUS, draws: int = 2, seed: int = 0) -> dict[str, torch.Tensor]:
    """Per window (b,) velocity MSE on steps context … t − 1 of latents x (b, v, t, C, h, w) under each variant,
    averaged over the flow times `taus` and `draws` noise draws per time (the same noise for every variant)."""
    tables = flow_loss_table(net, x, variants, context, taus, draws, seed)
    return {name: table.mean(dim=(1, 2)) for name, table in tables.items()}


def every_window(folder: str | Path, steps: int, fields: Sequence[str]) -> dict[str, Any]:
    """One batch of every `steps`-step window at every start of every clip of a latent cache split `folder`, with
    "open_loop" (b,) bool: the window's clip leaves its policy for a random command (meta.open_loop)."""
    encoder = MetadataEncoder(list(fields))
    clips = [read_latent_clip(path) for path in find_latent_clips(folder)]  # none: a ClipError naming the folder
    starts = [(clip, start) for clip in clips for start in range(clip.mean.shape[1] - steps + 1)]
    batch = collate_latent_windows([latent_window(clip, start, steps, encoder) for clip, start in starts])
    batch["open_loop"] = torch.tensor([bool(clip.meta.get("open_loop", False)) for clip, _ in starts])
    return batch


def condition_gain_report(net: LatentWorldModel, batch: dict[str, Any], latent_scale: float, context: int,
                          taus: Sequence[float] = TAUS) -> dict[str, Any]:
    """Losses of `action_variants` on a latent-window batch, what each saves over "neither", the action
    discrimination (swapped minus own actions, with and without agents) and the same per action component (only
    that column swapped, agents given), also per flow time τ, per generated step and per kind of clip (open-loop or
    policy; `every_window`'s "open_loop"), to say where in the sampler, how far ahead and on which windows each
    component is read; ± 95 % intervals over windows. `taus`: the flow times scored (a rollout lays out its frames
    near τ = 0, where the default TAUS do not look)."""
    if not taus or any(not 0.0 <= tau < 1.0 for tau in taus):
        raise ValueError(f"flow times to score: expected values in [0, 1) (1 is the clean latent), got {list(taus)}")
    x = batch["mean"] * latent_scale
    tables = flow_loss_table(net, x, action_variants(batch_conditions(batch)), context, taus)
    losses = {name: table.mean(dim=(1, 2)) for name, table in tables.items()}
    report: dict[str, Any] = {"windows": int(x.shape[0]), "context": context, "taus": [float(t) for t in taus],
                              "losses": {}, "gain_over_neither": {},
                              "action_discrimination": {}, "component_discrimination": {},
                              "component_discrimination_by_tau": {}, "component_discrimination_by_step": {},
                              "component_discrimination_by_clip": {}}
    for name, loss in losses.items():
        report["losses"][name] = float(loss.mean())
        report["gain_over_neither"][name] = asdict(mean_interval((losses["neither"] - loss).tolist()))
    for agents, (own, other) in {"with agents": ("actions and agents", "swapped actions and agents"),
                                 "without agents": ("actions only", "swapped actions only")}.items():
        report["action_discrimination"][agents] = asdict(mean_interval((losses[other] - losses[own]).tolist()))
    for name in ACTION_COMPONENTS:
        gap = tables[f"swapped {name} and agents"] - tables["actions and agents"]  # (b, taus, generated steps)
        report["component_discrimination"][name] = asdict(mean_interval(gap.mean(dim=(1, 2)).tolist()))
        report["component_discrimination_by_tau"][name] = {
            str(tau): asdict(mean_interval(gap[:, i].mean(dim=1).tolist())) for i, tau in enumerate(taus)}
        report["component_discrimination_by_step"][name] = {
            str(context + k): asdict(mean_interval(gap[:, :, k].mean(dim=1).tolist())) for k in range(gap.shape[2])}
        report["component_discrimination_by_clip"][name] = clip_kind_intervals(gap.mean(dim=(1, 2)),
                                                                               batch.get("open_loop"))
    return report


def clip_kind_intervals(values: torch.Tensor, open_loop: torch.Tensor | None) -> dict[str, Any]:
    """Per-window values (b,) averaged over the windows of open-loop clips and of policy clips apart (a kind with no
    window is left out): a model that reads a command as a cause shows it on the open-loop clips, where the
    context frames do not give the command away."""
    if open_loop is None:
        return {}
    kinds = {"open-loop clips": open_loop, "policy clips": ~open_loop}
    return {kind: asdict(mean_interval(values[mask].tolist())) for kind, mask in kinds.items() if bool(mask.any())}
