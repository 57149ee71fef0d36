"""Encode throughput of the GAIA-1 tokenizer's encoder vs a plain strided-conv encoder of equal FLOPs.

    python benchmarks/bench_tokenizer_encoder.py                       # 288x512, width 32 (paper 160)
    python benchmarks/bench_tokenizer_encoder.py --channels 16 --batch 2 --iters 3

Both encoders map (b, 3, 288, 512) to (b, 512, 18, 32) (D = 16, GAIA-1 §4.1). The paper-shaped one is
`ConvEncoder` with the paper preset's stage multipliers (1, 2, 4, 4, 8), two residual blocks per stage,
GroupNorm and SiLU, at a reduced base width. The plain one is four stride-2 3×3 convolutions with
SiLU, widths w·(1, 2, 4, 8), then a 1×1 to the latent; w is picked so that its multiply-accumulates
match the paper-shaped encoder's as closely as an integer width allows. Both are timed in one run,
interleaved, on the same thread count; frames/s are the best of `--iters` timed passes.
"""

from __future__ import annotations

import argparse
import time

import torch
from torch import nn

from gaia_app.nn.conv import ConvEncoder

PAPER_MULTS = (1, 2, 4, 4, 8)


def plain_encoder(width: int, latent_dim: int) -> nn.Sequential:
    """Four stride-2 3×3 convs (D = 16), widths width·(1, 2, 4, 8), SiLU between, then a 1×1 to the latent."""
    widths, layers, prev = [width * m for m in (1, 2, 4, 8)], [], 3
    for w in widths:
        layers += [nn.Conv2d(prev, w, 3, stride=2, padding=1), nn.SiLU()]
        prev = w
    return nn.Sequential(*layers, nn.Conv2d(prev, latent_dim, 1))


def conv_macs(model: nn.Module, x: torch.Tensor) -> int:
    """Multiply-accumulates of every Conv2d in one forward pass of `x` (other layers are negligible)."""
    total = 0

    def hook(module: nn.Conv2d, _inputs, output: torch.Tensor) -> None:
        nonlocal total
        k = module.kernel_size[0] * module.kernel_size[1] * module.in_channels // module.groups
        total += output.numel() * k

    handles = [m.register_forward_hook(hook) for m in model.modules() if isinstance(m, nn.Conv2d)]
    with torch.no_grad():
        model(x)
    for h in handles:
        h.remove()
    return total


def matched_plain(target_macs: int, latent_dim: int, probe: torch.Tensor) -> tuple[nn.Module, int]:
    """The plain encoder whose MACs are closest to `target_macs`, and its width."""
    # MACs depend on shapes only: count them on the meta device, without computing anything
    with torch.device("meta"):
        meta_probe = torch.empty(probe.shape)
        best = min(range(4, 1025, 2),
                   key=lambda w: abs(conv_macs(plain_encoder(w, latent_dim), meta_probe) - target_macs))
    return plain_encoder(best, latent_dim), best


@torch.inference_mode()
def frames_per_second(model: nn.Module, x: torch.Tensor) -> float:
    """Frames per second of one forward pass (no grad)."""
    start = time.perf_counter()
    model(x)
    return len(x) / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--channels", type=int, default=32, help="base width of the paper-shaped encoder (paper 160)")
    parser.add_argument("--latent-dim", type=int, default=512)
    parser.add_argument("--height", type=int, default=288)
    parser.add_argument("--width", type=int, default=512)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--iters", type=int, default=5)
    args = parser.parse_args()
    torch.manual_seed(0)
    x = torch.randn(args.batch, 3, args.height, args.width)
    probe = x[:1]
    paper = ConvEncoder(3, args.latent_dim, args.channels, PAPER_MULTS, blocks_per_stage=2).eval()
    macs = conv_macs(paper, probe)
    plain, plain_width = matched_plain(macs, args.latent_dim, probe)
    plain.eval()
    encoders = {"paper-shaped": paper, "plain strided": plain}
    for model in encoders.values():  # warm-up (allocator, oneDNN kernels)
        frames_per_second(model, x)
    best = {name: 0.0 for name in encoders}
    for _ in range(args.iters):
        for name, model in encoders.items():
            best[name] = max(best[name], frames_per_second(model, x))
    print(f"{args.height}x{args.width}, batch {args.batch}, {torch.get_num_threads()} threads, best of {args.iters}")
    for name, model in encoders.items():
        params = sum(p.numel() for p in model.parameters())
        g = conv_macs(model, probe) / 1e9
        print(f"  {name:14s} {params / 1e6:6.2f}M params  {g:6.2f} GMAC/frame  {best[name]:7.2f} frames/s")
    print(f"  plain width {plain_width}; "
          f"paper-shaped / plain throughput = {best['paper-shaped'] / best['plain strided']:.2f}")


if __name__ == "__main__":
    main()
