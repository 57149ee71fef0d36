"""GAIA-2 latent world model sampling cost: no guidance vs full CFG vs spatially selective CFG (GAIA-2 report,
inference), measured side by side in one run.

    python benchmarks/bench_latent_world_model_sampling.py                   # tiny preset, 3 cameras, 64×112
    python benchmarks/bench_latent_world_model_sampling.py --preset mid      # 224×448 rig, dim 256, depth 8

Random (perturbed) weights; a 3-camera front rig; two cars ahead and one to the side as the agent condition;
`--steps` Euler steps of the linear-quadratic schedule over `--latent-steps` latent steps from scratch.
Reports seconds per sample, the evaluated tokens (TokenCounter) and both as ratios to unguided sampling.
Selective CFG evaluates the second pass only on the tokens inside the projected agent boxes, so its cost
ratio sits between 1 and full CFG's 2 by the share of covered tokens.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from gaia_app.data.synthetic.rig import build_rig
from gaia_app.diffusion.flow_matching import FlowSampler
from gaia_app.models.gaia2.conditioning import AgentBoxes3d, WorldConditions
from gaia_app.pipelines.gaia2_world_model import Guidance, LatentWorldModelPipeline, agent_token_positions

NET = Path(__file__).resolve().parents[1] / "conf" / "model" / "net" / "gaia2_world_model_tiny.yaml"
PRESETS = {"tiny": {"size": (64, 112), "net": {}}, "mid": {"size": (224, 448), "net": {"dim": 256, "depth": 8}}}


def build(preset: str) -> tuple[torch.nn.Module, tuple[int, int]]:
    torch.manual_seed(0)
    cfg = OmegaConf.merge(OmegaConf.load(NET), PRESETS[preset]["net"])
    net = instantiate(cfg)()
    with torch.no_grad():  # zero-initialised output layers would make every guidance pass trivially equal
        for p in net.parameters():
            p.add_(0.02 * torch.randn_like(p))
    return net.eval(), PRESETS[preset]["size"]


def conditions(size: tuple[int, int], steps: int) -> WorldConditions:
    specs = build_rig(["front", "front_left", "front_right"], *size)
    intrinsics = torch.from_numpy(np.stack([c.intrinsics for c in specs])).float()[None]
    extrinsics = torch.from_numpy(np.stack([c.extrinsics for c in specs])).float()[None]
    centres = torch.tensor([[14.0, 0.0, 0.8], [25.0, 3.5, 0.8], [6.0, -4.0, 0.8]])
    n = len(centres)
    agents = AgentBoxes3d(centres.expand(1, steps, n, 3), torch.tensor([4.5, 1.9, 1.6]).expand(1, steps, n, 3),
                          torch.zeros(1, steps, n), torch.zeros(1, steps, n, dtype=torch.long),
                          torch.ones(1, steps, n, dtype=torch.bool))
    return WorldConditions(intrinsics, extrinsics, size, timestamps=torch.arange(steps)[None].float() * 0.32,
                           actions=torch.tensor([[8.0, 0.0]]).expand(1, steps, 2), agents=agents)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", choices=sorted(PRESETS), default="tiny")
    parser.add_argument("--steps", type=int, default=20, help="Euler steps")
    parser.add_argument("--latent-steps", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_grad_enabled(False)
    net, size = build(args.preset)
    cond = conditions(size, args.latent_steps)
    h, w = size[0] // 8, size[1] // 8  # the video tokenizer's 8× spatial compression
    shape = (1, 3, args.latent_steps, net.latent_channels, h, w)
    covered = agent_token_positions(cond, (h, w), net.patch).numel()
    total = 3 * (h // net.patch) * (w // net.patch)
    rows = {"no guidance": Guidance(), "full CFG ×4": Guidance(4.0), "selective CFG ×4": Guidance(4.0, spatial=True),
            "selective CFG ×4, paired agent passes": Guidance(4.0, spatial=True, spatial_pass="paired")}
    seconds = {name: [] for name in rows}
    tokens = {}
    for _ in range(args.repeats):  # interleaved, so machine noise hits every row alike
        for name, guidance in rows.items():
            pipe = LatentWorldModelPipeline(net, FlowSampler(steps=args.steps), guidance)
            start = time.perf_counter()
            pipe.from_scratch(shape, cond, torch.Generator().manual_seed(0))
            seconds[name].append(time.perf_counter() - start)
            tokens[name] = pipe.counter.tokens
    print(f"preset {args.preset}: {size[0]}×{size[1]} × 3 cameras, latents {shape[1:]}, {args.steps} Euler steps; "
          f"agent boxes cover {covered} of {total} token positions ({covered / total:.0%})")
    print("| sampling | s / sample (median) | × unguided | evaluated tokens | × unguided |")
    print("|---|---:|---:|---:|---:|")
    base_s, base_t = float(np.median(seconds["no guidance"])), tokens["no guidance"]
    for name in rows:
        s = float(np.median(seconds[name]))
        print(f"| {name} | {s:.3f} | {s / base_s:.2f} | {tokens[name]} | {tokens[name] / base_t:.2f} |")


if __name__ == "__main__":
    main()
