"""Issue 51, item 2 (GAIA-2): frames/s of a 3-camera rollout at the report's latent layout with a small net, at 50
Euler steps and at fewer. A check of `benchmarks/gpu_checks.py` ("gaia2_rollout"), or on its own:

    python benchmarks/gpu_gaia2_rollout.py                    # on the GPU machine
    python benchmarks/gpu_gaia2_rollout.py --dry-run          # tiny sizes on a CPU

The layout is the report's video tokenizer (conf/model/net/gaia2_video_tokenizer_paper.yaml): 64 latent channels,
14 × 30 latents per camera (448 × 960 pixels at 32× spatial compression), one latent step per 8 video frames. The net
is the tiny preset's design widened to 256 × 8 layers (patch 2: 3 × 7 × 15 = 315 tokens a latent step), with the
report's conditioning only (no rasters) and random weights, bf16 autocast on CUDA. A rollout: 2 context latent steps,
then 2 chunks of 2 new ones (`LatentWorldModelPipeline.rollout`), unguided. frames/s counts the video frames the new
latent steps stand for (8 each), per camera rig; the video decoder is not timed. Which step count keeps the rollouts'
FVMD within 10 % of 50 steps is a property of trained weights, measured on the CPU with the shipped ones
(`benchmarks/gaia2_euler_steps.py`: 5 steps, on two held-out worlds), so 5 is among the counts timed here.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import torch
from hydra.utils import instantiate
from lightning.fabric.utilities.apply_func import move_data_to_device
from omegaconf import OmegaConf

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_latent_world_model_sampling import NET, conditions  # noqa: E402  (the tiny design, a 3-camera rig)

from gaia_app.diffusion.flow_matching import FlowSampler  # noqa: E402
from gaia_app.pipelines.gaia2_world_model import LatentWorldModelPipeline  # noqa: E402

PAPER = {"channels": 64, "grid": (14, 30), "spatial": 32, "frames_per_latent": 8}
SMALL = {"dim": 256, "depth": 8, "heads": 4}
DRY = {"channels": 8, "grid": (4, 6), "net": {"dim": 32, "depth": 1, "heads": 2}}
STEPS = (50, 20, 10, 5)  # 5: the fewest that kept FVMD within 10 % (benchmarks/gaia2_euler_steps.py)


def build(dry_run: bool, device: torch.device) -> torch.nn.Module:
    """The small net at the layout's channel count, random (perturbed) weights: zero-initialised output layers
    would make every step trivially cheap to reason about but not to time."""
    torch.manual_seed(0)
    layout = {"latent_channels": DRY["channels"] if dry_run else PAPER["channels"],
              "agent_raster": False, "action_raster": False, **(DRY["net"] if dry_run else SMALL)}
    cfg = OmegaConf.merge(OmegaConf.load(NET), layout, {"text_dim": 0})
    net = instantiate(cfg)()
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.02 * torch.randn_like(p))
    return net.eval().to(device)


def rollout_seconds(pipe: LatentWorldModelPipeline, context: torch.Tensor, chunks: list, chunk_steps: int,
                    device: torch.device) -> float:
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    start = time.perf_counter()
    with torch.autocast(device.type, dtype=torch.bfloat16, enabled=device.type == "cuda"):
        pipe.rollout(context, chunks, chunk_steps, torch.Generator(device).manual_seed(0))
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter() - start


def measure(dry_run: bool, device: torch.device, steps_list: tuple[int, ...] = STEPS, repeats: int = 3,
            context_steps: int = 2, chunk_steps: int = 2, chunk_count: int = 2, save=None) -> dict[str, Any]:
    """Rows per Euler step count: seconds per rollout (median of `repeats` after one untimed), latent steps/s,
    video frames/s. `save(partial)` after each row."""
    net = build(dry_run, device)
    grid = DRY["grid"] if dry_run else PAPER["grid"]
    pixels = (grid[0] * PAPER["spatial"], grid[1] * PAPER["spatial"])
    cond = move_data_to_device(conditions(pixels, context_steps + chunk_steps), device)
    context = torch.randn(1, 3, context_steps, net.latent_channels, *grid, device=device)
    result: dict[str, Any] = {"layout": f"3 cameras × {net.latent_channels} × {grid[0]}×{grid[1]}",
                              "net": f"dim {net.dim}, depth {len(net.blocks)}",
                              "tokens_per_latent_step": 3 * (grid[0] // net.patch) * (grid[1] // net.patch),
                              "rows": {}}
    for steps in steps_list:
        pipe = LatentWorldModelPipeline(net, FlowSampler(steps=steps))
        chunks = [cond] * chunk_count
        rollout_seconds(pipe, context, chunks, chunk_steps, device)  # warm-up: kernels, allocator
        runs = [rollout_seconds(pipe, context, chunks, chunk_steps, device) for _ in range(repeats)]
        seconds, new = statistics.median(runs), chunk_steps * chunk_count
        result["rows"][f"{steps} Euler steps"] = {
            "seconds": seconds, "latent_steps_per_s": new / seconds,
            "frames_per_s": new * PAPER["frames_per_latent"] / seconds, "runs": [round(r, 4) for r in runs]}
        if save is not None:
            save(result)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dry-run", action="store_true")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json")
    args = parser.parse_args()
    device = torch.device("cuda" if torch.cuda.is_available() and not args.dry_run else "cpu")
    torch.set_grad_enabled(False)
    result = measure(args.dry_run, device, repeats=args.repeats)
    print(f"{result['layout']}, {result['net']}, {result['tokens_per_latent_step']} tokens a latent step, {device}")
    for name, row in result["rows"].items():
        print(f"{name}: {row['seconds']:.3f} s a rollout, {row['frames_per_s']:.1f} frames/s")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
