r"""Rate–distortion of the GAIA-2 video tokenizer next to the GAIA-1 image tokenizer, on the same held-out clips.

    python benchmarks/rate_distortion.py --gaia2-ckpt RUN2/checkpoints/last.ckpt [GAN_RUN/checkpoints/last.ckpt] \
        --gaia1-ckpt RUN1/checkpoints/last.ckpt

Held-out clips: the synthetic world with a seed no training run uses (--seed), the 3-camera front rig,
at the tokenizers' resolution. Rates are bits per frame pixel (bpp):
- GAIA-1: h·w tokens of log2(K) bits per frame (fixed-length code), and the same tokens at the
  empirical entropy of their codes on these clips (what an entropy coder would reach).
- GAIA-2: the posterior means stored at 16 bits (bf16), uniformly quantised to 8/4/3/2 bits per value
  (per-channel range over the clips; PSNR decoded from the quantised latents), and the KL to the prior
  (the bits-back rate of the Gaussian channel).
Distortion: PSNR and SSIM over every frame of every camera. Prints a Markdown table; --out writes it too.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import torch
from einops import rearrange
from tqdm import tqdm

from gaia_app.data.synthetic import SyntheticClipDataset
from gaia_app.data.transforms import to_float
from gaia_app.eval.metrics import psnr, ssim
from gaia_app.lit.checkpoint import load_module
from gaia_app.models.gaia2.video_tokenizer import VideoTokenizer, kl_bits_per_pixel

CAMERAS = ["front", "front_left", "front_right"]


def held_out_clips(n: int, seed: int, height: int, width: int, frames: int, fps: float) -> torch.Tensor:
    """(n, v, T, 3, H, W) float in [-1, 1] from the synthetic world."""
    source = SyntheticClipDataset(num_clips=n, seed=seed, height=height, width=width, cameras=CAMERAS, clip_len=frames,
                                  fps=fps)
    return torch.stack([to_float(torch.from_numpy(source[i].frames))
                        for i in tqdm(range(n), desc="render held-out clips")])


def distortion(recon: torch.Tensor, video: torch.Tensor) -> tuple[float, float]:
    """Mean PSNR (dB) and SSIM over frames; both (..., 3, H, W)."""
    a, b = recon.clamp(-1, 1).flatten(0, -4), video.flatten(0, -4)
    return float(psnr(a, b).mean()), float(ssim(a, b).mean())


def quantise(latents: torch.Tensor, bits: int, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    """Uniform `bits`-bit quantisation per channel over [low, high] (channel dim 3 of (b, v, t, C, h, w))."""
    levels = 2**bits - 1
    shape = (1, 1, 1, -1, 1, 1)
    low, high = low.view(shape), high.view(shape)
    step = (high - low).clamp_min(1e-8) / levels
    return ((latents.clamp(low, high) - low) / step).round() * step + low


@torch.no_grad()
def gaia2_rows(tokenizer: VideoTokenizer, clips: torch.Tensor, label: str) -> list[tuple[str, float, float, float]]:
    posteriors = [tokenizer.encode(clip[None]) for clip in tqdm(clips, desc="GAIA-2 encode")]
    means = torch.cat([p.mean for p in posteriors])
    channels = rearrange(means, "b v t c h w -> c (b v t h w)")
    low, high = channels.min(dim=1).values, channels.max(dim=1).values
    frames, height, width = clips.shape[2], clips.shape[-2], clips.shape[-1]
    rows = []
    for bits in (16, 8, 4, 3, 2):
        latents = means.bfloat16().float() if bits == 16 else quantise(means, bits, low, high)
        recon = torch.cat([tokenizer.decode(z[None]) for z in latents])
        p, s = distortion(recon, clips)
        rows.append((f"{label}, {bits}-bit{' (bf16)' if bits == 16 else ''}", tokenizer.storage_bits_per_pixel(bits),
                     p, s))
    kl = float(np.mean([kl_bits_per_pixel(q, frames, height, width) for q in posteriors]))
    # the bits-back rate codes the means themselves: their distortion is the bf16 row's (bf16 rounding is below 0.01 dB)
    rows.append((f"{label}, KL rate (bits-back)", kl, rows[0][2], rows[0][3]))
    return rows


@torch.no_grad()
def gaia1_rows(tokenizer, clips: torch.Tensor) -> list[tuple[str, float, float, float]]:
    frames = rearrange(clips, "b v t c h w -> (b v t) c h w")
    tokens = torch.cat([tokenizer.encode(chunk) for chunk in tqdm(frames.split(32), desc="GAIA-1 encode")])
    recon = torch.cat([tokenizer.decode(chunk) for chunk in tokens.split(32)])
    p, s = distortion(recon, frames)
    pixels = frames.shape[-2] * frames.shape[-1]
    fixed = tokens[0].numel() * math.log2(tokenizer.codebook_size) / pixels
    counts = torch.bincount(tokens.flatten(), minlength=tokenizer.codebook_size).double()
    probs = counts[counts > 0] / counts.sum()
    entropy = float(-(probs * probs.log2()).sum()) * tokens[0].numel() / pixels
    return [(f"GAIA-1 tokens, log2 K = {math.log2(tokenizer.codebook_size):.0f} bits each", fixed, p, s),
            ("GAIA-1 tokens, empirical code entropy", entropy, p, s)]


def table(rows: list[tuple[str, float, float, float]], header: str) -> str:
    lines = [header, "", "| representation | bits / pixel | PSNR (dB) | SSIM |", "|---|---:|---:|---:|"]
    lines += [f"| {name} | {bpp:.3f} | {p:.2f} | {s:.3f} |" for name, bpp, p, s in rows]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--gaia2-ckpt", required=True, nargs="+", help="one or more GAIA-2 tokenizer checkpoints")
    parser.add_argument("--gaia1-ckpt", default=None, help="GAIA-1 tokenizer at the same resolution (optional)")
    parser.add_argument("--clips", type=int, default=16)
    parser.add_argument("--frames", type=int, default=8, help="frames per clip (a multiple of τ)")
    parser.add_argument("--fps", type=float, default=12.5)
    parser.add_argument("--height", type=int, default=64)
    parser.add_argument("--width", type=int, default=112)
    parser.add_argument("--seed", type=int, default=777_777, help="synthetic world seed of the held-out clips")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    torch.manual_seed(0)
    clips = held_out_clips(args.clips, args.seed, args.height, args.width, args.frames, args.fps)
    rows = []
    for ckpt in args.gaia2_ckpt:
        rows += gaia2_rows(load_module(ckpt).tokenizer, clips, f"GAIA-2 latents ({Path(ckpt).parent.parent.name})")
    if args.gaia1_ckpt:
        rows += gaia1_rows(load_module(args.gaia1_ckpt).tokenizer, clips)
    header = (f"{args.clips} held-out synthetic clips (seed {args.seed}) × {len(CAMERAS)} cameras × "
              f"{args.frames} frames "
              f"at {args.height}×{args.width}, {args.fps:g} Hz")
    text = table(rows, header)
    print(text)
    if args.out:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
