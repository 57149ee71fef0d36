"""Encode and decode throughput (frames/s) of the GAIA-2 video tokenizer at tiny and mid sizes,
side by side with the GAIA-1 image tokenizer on the same frames.

    python benchmarks/bench_video_tokenizer.py                 # CPU, both sizes
    python benchmarks/bench_video_tokenizer.py --device cuda --dtype bfloat16 --sizes tiny mid paper

Sizes (untrained weights; speed does not depend on them):
- tiny:  conf/model/net/gaia2_video_tokenizer_tiny.yaml on 3 cameras × 8 frames of 64×112, against the
         tiny GAIA-1 tokenizer (conf/model/net/gaia1_tokenizer_tiny.yaml) on the same 24 frames.
- mid:   the paper preset's layout at a quarter of its widths, 16× / 8× downsampling, 3 cameras × 8 frames of
         224×448, against the GAIA-1 tokenizer paper layout at a quarter of its width (D = 16).
- paper: conf/model/net/gaia2_video_tokenizer_paper.yaml, 1 camera × 24 frames of 448×960 (GPU), against the
         GAIA-1 paper tokenizer on the same frames.
Each measurement is the best of --iters timed passes after one warm-up, interleaved so both tokenizers see
the same machine state; the ratio column is GAIA-2 frames/s over GAIA-1 frames/s in the same run.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path

import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from gaia_app.models.gaia1.tokenizer import ImageTokenizer
from gaia_app.models.gaia2.video_tokenizer import VideoTokenizer

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"


def net_config(name: str, **overrides) -> dict:
    cfg = OmegaConf.to_container(OmegaConf.load(CONF_DIR / "model" / "net" / f"{name}.yaml"))
    cfg.pop("_partial_")
    cfg.update(overrides)
    return cfg


def sizes() -> dict[str, tuple[dict, dict, tuple[int, int, int, int]]]:
    """name → (GAIA-2 net config, GAIA-1 net config, (views, frames, H, W))."""
    mid2 = net_config("gaia2_video_tokenizer_paper", spatial_downsampling=16, conv_mults=[1, 2, 4], conv_channels=16,
                      encoder_dim=192, encoder_heads=3, decoder_dim=256, decoder_heads=4, decoder_conv_channels=8,
                      checkpointing=False)
    mid1 = net_config("gaia1_tokenizer_paper", channels=40)
    return {
        "tiny": (net_config("gaia2_video_tokenizer_tiny"), net_config("gaia1_tokenizer_tiny"), (3, 8, 64, 112)),
        "mid": (mid2, mid1, (3, 8, 224, 448)),
        "paper": (net_config("gaia2_video_tokenizer_paper", checkpointing=False), net_config("gaia1_tokenizer_paper"),
                  (1, 24, 448, 960)),
    }


def best_seconds(fn: Callable[[], object], iters: int, device: torch.device) -> float:
    fn()  # warm-up
    times = []
    for _ in range(iters):
        if device.type == "cuda":
            torch.cuda.synchronize()
        start = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - start)
    return min(times)


@torch.inference_mode()
def measure(name: str, iters: int, device: torch.device, dtype: torch.dtype) -> list[str]:
    cfg2, cfg1, (views, frames, height, width) = sizes()[name]
    gaia2 = instantiate(cfg2).to(device, dtype).eval()
    gaia1 = instantiate(cfg1).to(device, dtype).eval()
    assert isinstance(gaia2, VideoTokenizer) and isinstance(gaia1, ImageTokenizer)
    video = torch.rand(1, views, frames, 3, height, width, device=device, dtype=dtype) * 2 - 1
    images = video.flatten(0, 2)
    latents = gaia2.encode(video).mean
    tokens = gaia1.encode(images)
    n = views * frames
    fps = {
        "encode": (n / best_seconds(lambda: gaia2.encode(video), iters, device),
                   n / best_seconds(lambda: gaia1.encode(images), iters, device)),
        "decode": (n / best_seconds(lambda: gaia2.decode(latents), iters, device),
                   n / best_seconds(lambda: gaia1.decode(tokens), iters, device)),
    }
    params2 = sum(p.numel() for p in gaia2.parameters()) / 1e6
    params1 = sum(p.numel() for p in gaia1.parameters()) / 1e6
    return [f"| {name} | {views}×{frames} @ {height}×{width} | {op} | {g2:.1f} | {g1:.1f} | {g2 / g1:.2f} | "
            f"{params2:.1f}M / {params1:.1f}M |" for op, (g2, g1) in fps.items()]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", nargs="+", default=["tiny", "mid"], choices=["tiny", "mid", "paper"])
    parser.add_argument("--iters", type=int, default=3)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dtype", default="float32", choices=["float32", "bfloat16"])
    args = parser.parse_args()
    device, dtype = torch.device(args.device), getattr(torch, args.dtype)
    print(f"device {device}, {args.dtype}, {torch.get_num_threads()} threads")
    print("| size | views×frames @ H×W | op | GAIA-2 frames/s | GAIA-1 frames/s | ratio | params GAIA-2 / GAIA-1 |")
    print("|---|---|---|---:|---:|---:|---|")
    for name in args.sizes:
        for line in measure(name, args.iters, device, dtype):
            print(line, flush=True)


if __name__ == "__main__":
    main()
