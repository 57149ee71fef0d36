r"""GAIA-2: where does the agents' cross-attention look, and how much do the agents move the prediction?
(paper-faithful issue, diagnosis of the agent path)

    python benchmarks/gaia2_agent_attention.py --weights A [B ...] --latents <latent cache>/val [--windows 16]
        [--json OUT]

For each weights folder, on the first `--windows` clips of a held-out latent cache (each clip's first
`model.steps` latent steps with their own agents), all steps noised to flow time τ = 0.5 with one fixed noise:

- per block, the cross-attention mass that image tokens give the agent tokens (averaged over heads), for tokens inside
  a visible agent box of their own camera and for tokens outside every box; for the inside tokens also the mass on the
  agents whose boxes cover them ("own agent"); beside it the share a uniform attention over the keys an inside token
  may read would give the agents (with `agent_box_attention` only those over it);
- the agents' effect on the prediction: RMS of v(agents) − v(agents dropped) inside and outside the boxes, over the RMS
  of v. A conditioning path that localises puts its mass and its effect inside the boxes.

GAIA-2 report, world model: agents reach the net through cross-attention only. Our agent raster (`agent_raster`)
paints them on the grid instead; a folder with it still reports its cross-attention.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import torch
from einops import rearrange
from tqdm import tqdm

from gaia_app.data.latent_cache import find_latent_clips, read_latent_clip
from gaia_app.models.gaia2.conditioning import own_camera_coverage
from gaia_app.models.gaia2.latent_world_model import LatentWorldModel
from gaia_app.nn.spacetime import CrossAttention
from gaia_app.pipelines.gaia2 import Gaia2Pipeline
from gaia_app.utils.run_dir import atomic_write_text

TAU = 0.5


class AttentionRecorder:
    """Forward hooks on every block's CrossAttention: the softmax weights (B, heads, n, m) of each call."""

    def __init__(self, net: LatentWorldModel):
        self.weights: list[torch.Tensor] = []
        self.keys: list[torch.Tensor] = []  # the keys each query may read (B, n, m)
        self.handles = [block.cross.register_forward_hook(self.record) for block in net.blocks]

    def record(self, module: CrossAttention, inputs: tuple, _output: torch.Tensor) -> None:
        x, context, mask = inputs
        q = rearrange(module.to_q(x), "b n (h e) -> b h n e", h=module.heads)
        k, _ = rearrange(module.to_kv(context), "b m (two h e) -> two b h m e", two=2, h=module.heads)
        logits = torch.einsum("bhne,bhme->bhnm", q.float(), k.float()) / q.shape[-1] ** 0.5
        if mask is not None:
            keys = mask[:, None, None, :] if mask.ndim == 2 else mask[:, None]  # (B, m) or per query (B, n, m)
            logits = logits.masked_fill(~keys, float("-inf"))
            self.keys.append(keys[:, 0].expand(-1, x.shape[1], -1))
        else:
            self.keys.append(torch.ones(x.shape[0], x.shape[1], context.shape[1], dtype=torch.bool))
        self.weights.append(logits.softmax(dim=-1))

    def close(self) -> None:
        for handle in self.handles:
            handle.remove()


def token_coverage(net: LatentWorldModel, cond: Any, grid: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """(t, v·gh·gw, v·N) bool: agent j's box covers image token i in i's own camera; and (t, v·N) visible."""
    _, boxes, visible = net.conditioner.agent_features(cond, grid)  # boxes (1, t, v, N, 4), visible (1, t, v, N)
    return own_camera_coverage(boxes, visible, grid)[0], rearrange(visible[0], "t v n -> t (v n)")


def window_report(net: LatentWorldModel, x: torch.Tensor, cond: Any, noise_seed: int) -> dict[str, Any] | None:
    """One window's attention masses per block and the agents' effect; None when no agent box is visible or every
    token is under one. x (1, v, t, C, h, w) scaled latents, cond their WorldConditions."""
    if cond.agents is None:
        return None
    _, v, t, _, h, w = x.shape
    grid = (h // net.patch, w // net.patch)
    own, visible = token_coverage(net, cond, grid)
    inside = own.any(dim=-1)  # (t, n)
    if not inside.any() or inside.all():
        return None
    noise = torch.randn(x.shape, generator=torch.Generator().manual_seed(noise_seed)).to(x.dtype)
    x_tau = TAU * x + (1 - TAU) * noise
    tau = torch.full((1, t), TAU)
    recorder = AttentionRecorder(net)
    with torch.no_grad():
        with_agents = net(x_tau, tau, cond)
        recorder.close()
        without = net(x_tau, tau, cond.without("agents"))
    agents = slice(1, 1 + visible.shape[-1])  # the context: null, agents (v·N), metadata, text
    blocks = []
    for weights, keys in zip(recorder.weights, recorder.keys):
        mass = weights.mean(dim=1)  # (t, n, m): batch 1, so (b t) = t
        on_agents = mass[..., agents].sum(-1)
        on_own = (mass[..., agents] * own).sum(-1)
        uniform = keys[..., agents].sum(-1) / keys.sum(-1)  # the agents' share of the keys a token may read
        blocks.append({"inside": float(on_agents[inside].mean()), "outside": float(on_agents[~inside].mean()),
                       "own_inside": float(on_own[inside].mean()), "uniform": float(uniform[inside].mean())})
    cells = rearrange(inside, "t (v h w) -> v t h w", v=v, h=grid[0])
    cells = cells.repeat_interleave(net.patch, -2).repeat_interleave(net.patch, -1)[None, :, :, None]
    cells = cells.expand_as(with_agents)
    scale = with_agents.pow(2).mean().sqrt()
    change = (with_agents - without).pow(2)
    return {"blocks": blocks, "effect_inside": float(change[cells].mean().sqrt() / scale),
            "effect_outside": float(change[~cells].mean().sqrt() / scale)}


def folder_report(weights: str, latents: Path, windows: int, steps: int, seed: int) -> dict[str, Any]:
    pipeline = Gaia2Pipeline.from_weights(weights)
    folders = find_latent_clips(latents)[:windows]
    if not folders:
        raise ValueError(f"--latents {latents}: no latent clips found")
    net: LatentWorldModel = pipeline.world.model
    rows = []
    for i, folder in enumerate(tqdm(folders, desc=str(weights))):
        row = window_report(net, *pipeline.window(read_latent_clip(folder), 0, steps), seed + i)
        if row is not None:
            rows.append(row)
    if not rows:
        raise ValueError(f"--latents {latents}: none of the first {windows} clips has a visible agent box")
    return {"weights": str(weights), **pooled(rows)}


def pooled(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The mean over windows of `window_report` rows."""
    depth = len(rows[0]["blocks"])
    mean = lambda key, b: sum(r["blocks"][b][key] for r in rows) / len(rows)  # noqa: E731
    return {"windows": len(rows),
            "blocks": [{k: mean(k, b) for k in ("inside", "outside", "own_inside", "uniform")} for b in range(depth)],
            "effect_inside": sum(r["effect_inside"] for r in rows) / len(rows),
            "effect_outside": sum(r["effect_outside"] for r in rows) / len(rows)}


def markdown(reports: list[dict[str, Any]]) -> str:
    lines = [f"Agent cross-attention at τ = {TAU} (mass on agent tokens, mean over heads, tokens and windows)", "",
             "| weights | block | inside boxes | own agent (inside) | outside boxes | uniform |",
             "|---|---:|---:|---:|---:|---:|"]
    for r in reports:
        for b, row in enumerate(r["blocks"]):
            lines.append(f"| {r['weights']} | {b} | {row['inside']:.3f} | {row['own_inside']:.3f} | "
                         f"{row['outside']:.3f} | {row['uniform']:.3f} |")
    lines += ["", "| weights | windows | effect of the agents inside boxes | outside |", "|---|---:|---:|---:|"]
    lines += [f"| {r['weights']} | {r['windows']} | {r['effect_inside']:.4f} | {r['effect_outside']:.4f} |"
              for r in reports]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", nargs="+", required=True, help="GAIA-2 weights folders (gaia2 or paths)")
    parser.add_argument("--latents", type=Path, required=True, help="a latent cache split (generate.py mode=encode)")
    parser.add_argument("--windows", type=int, default=16)
    parser.add_argument("--steps", type=int, default=4, help="latent steps per window (the training window)")
    parser.add_argument("--seed", type=int, default=0, help="noise seed of the first window")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    reports = [folder_report(w, args.latents, args.windows, args.steps, args.seed) for w in args.weights]
    print(markdown(reports))
    if args.json:
        atomic_write_text(args.json, json.dumps(reports, indent=2) + "\n")
    return reports


if __name__ == "__main__":
    main()
