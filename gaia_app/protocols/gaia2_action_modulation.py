"""How far a commanded contrast moves a GAIA-2 world model's AdaLN modulation (issue 50, "diagnose before you scale":
the action's share of the residual stream).

Legend: C commands, n start speeds, g generated latent steps, k flow times, B blocks, d width.

GAIA-2 conditions on the ego action through AdaLN only (the report's design; models/gaia2/conditioning.py: per latent
step c = MLP(τ) + MLP(action)). Every block turns c into the shifts, scales and gates of its sublayers
(nn/spacetime.py, 9·d numbers), and the output layer into a shift and a scale (2·d). So the command reaches the
picture only through how much it changes these. For the two commands of a contrast (accelerate − brake speed,
left − right curvature, chosen by `contrast_pairs` as the action table chooses them) from one start speed, at each
generated latent step and flow time τ:

    features    = |φ(high) − φ(low)|: the distance of the Fourier features the action MLP reads (no weights);
    conditioner = |c(high) − c(low)| ÷ |c(mid)|        mid: the two commands' mean action;
    block b     = |m_b(c(high)) − m_b(c(low))| ÷ |m_b(c(mid))|, b = 1 … B and the output layer (relative), and
                  the numerator alone (absolute: a net whose modulations grow also grows its |m_b(c(mid))|);

0 where the modulation ignores the command. No data, no sampling: the numbers are read off the net's weights for
the actions the action table commands (`future_actions`, averaged over each latent step's frames as the latent
windows average them), so they can be compared across budgets for free. A contrast the net draws changes its
modulation; one it does not may still be carried by the net through the context (this readout does not see that).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from einops import reduce

from gaia_app.eval.controllability import contrast_pairs
from gaia_app.pipelines.gaia1_inputs import future_actions

CONTRAST_NAMES = ("speed", "curvature")


def step_actions(commands: Sequence[Sequence[str]], start_speed: float, steps: int, frames_per_step: int,
                 rate: float) -> torch.Tensor:
    """(C, g, 2): each command's (speed m/s, curvature 1/m) from `start_speed`, per frame at `rate` Hz from the
    first generated frame on, averaged over each of the `steps` latent steps of `frames_per_step` frames."""
    per_frame = np.stack([future_actions(speed, curvature, steps * frames_per_step, rate, start_speed)
                          for speed, curvature in commands])
    return reduce(torch.from_numpy(per_frame).double(), "c (g f) a -> c g a", "mean", f=frames_per_step)


def modulations(net: torch.nn.Module, c: torch.Tensor) -> torch.Tensor:
    """(B + 1, …, 9·d) every block's AdaLN modulation of c (…, d), then the output layer's (2·d, zero-padded)."""
    blocks = [block.modulation(c) for block in net.blocks]
    out = net.modulation_out(c)
    pad = blocks[0].shape[-1] - out.shape[-1] if blocks else 0
    return torch.stack([*blocks, torch.nn.functional.pad(out, (0, pad))])


def relative_change(high: torch.Tensor, low: torch.Tensor, mid: torch.Tensor) -> torch.Tensor:
    """|high − low| ÷ |mid| over the last dimension."""
    return (high - low).norm(dim=-1) / mid.norm(dim=-1).clamp_min(1e-12)


@torch.no_grad()
def modulation_contrast(net: torch.nn.Module, high: torch.Tensor, low: torch.Tensor, taus: Sequence[float]
                        ) -> dict[str, torch.Tensor]:
    """{"features": (g,), "conditioner": (k, g), "blocks" and "blocks_change": (k, g, B + 1)} for the actions (g, 2) of
    two commands (module docstring); the last of the B + 1 is the output layer."""
    conditioner = net.conditioner
    param = next(net.parameters())
    tau = torch.tensor(list(taus), dtype=param.dtype)[:, None, None]  # (k, 1, 1): broadcast over the steps
    start = conditioner.tau_embedding(tau[..., 0])  # (k, 1, d)
    embedded = {name: start + conditioner.action_embedding(actions.to(param.dtype))[None]  # (k, g, d)
                for name, actions in (("high", high), ("low", low), ("mid", (high + low) / 2))}
    mods = {name: modulations(net, c) for name, c in embedded.items()}  # (B + 1, k, g, 9·d)
    features = conditioner.action_features(high.to(param.dtype)) - conditioner.action_features(low.to(param.dtype))
    return {"features": features.norm(dim=-1).double(),
            "conditioner": relative_change(embedded["high"], embedded["low"], embedded["mid"]).double(),
            "blocks": relative_change(mods["high"], mods["low"], mods["mid"]).permute(1, 2, 0).double(),
            "blocks_change": (mods["high"] - mods["low"]).norm(dim=-1).permute(1, 2, 0).double()}


def action_modulation(net: torch.nn.Module, commands: Sequence[Sequence[str]], start_speeds: Sequence[float],
                      steps: int, frames_per_step: int, rate: float, taus: Sequence[float]) -> dict[str, Any]:
    """Per contrast (speed, curvature): the commands compared; the feature distance ([start speed][step]); the
    conditioner's relative change ([start speed][τ][step]); each block's relative and absolute change
    ([start speed][τ][step][block], the output layer last); and their means over start speeds, τ and steps, with the
    smallest and largest of the grid, for the features, the conditioner, the blocks' mean (relative and absolute) and
    the output layer (relative)."""
    if not start_speeds or not taus:
        raise ValueError("the action modulation needs at least one start speed and one flow time")
    actions = torch.stack([step_actions(commands, v, steps, frames_per_step, rate) for v in start_speeds], dim=1)
    pairs = contrast_pairs(actions)  # (C, n, g, 2) → (high, low) per channel, as the action table pairs them
    out: dict[str, Any] = {}
    for name, (high, low) in zip(CONTRAST_NAMES, pairs):
        grids = [modulation_contrast(net, actions[high, i], actions[low, i], taus) for i in range(len(start_speeds))]
        stacked = {key: torch.stack([grid[key] for grid in grids]) for key in grids[0]}  # (n, …) each
        blocks, change = stacked["blocks"], stacked["blocks_change"]  # (n, k, g, B + 1)
        out[name] = {"commands": ["/".join(commands[high]), "/".join(commands[low])],
                     **{key: value.tolist() for key, value in stacked.items()},
                     "summary": {"features": spread(stacked["features"]),
                                 "conditioner": spread(stacked["conditioner"]),
                                 "blocks_mean": spread(blocks[..., :-1].mean(-1)),
                                 "blocks_mean_change": spread(change[..., :-1].mean(-1)),
                                 "output": spread(blocks[..., -1])}}
    return out


def spread(values: torch.Tensor) -> dict[str, float]:
    """{mean, min, max} of a grid of readings."""
    return {"mean": float(values.mean()), "min": float(values.min()), "max": float(values.max())}
