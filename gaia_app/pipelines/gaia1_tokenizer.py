"""Inference with the GAIA-1 image tokenizer: video → tokens → reconstruction (GAIA-1 §2.2)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from einops import rearrange

from gaia_app.eval.metrics import psnr, ssim
from gaia_app.models.gaia1.tokenizer import ImageTokenizer


@dataclass
class ReconstructionOutput:
    """tokens: (v, t, h, w) int64; reconstruction: (v, t, 3, H, W) in [-1, 1];
    psnr, ssim: (v, t) per-frame scores against the input."""

    tokens: torch.Tensor
    reconstruction: torch.Tensor
    psnr: torch.Tensor
    ssim: torch.Tensor


class TokenizerReconstructionPipeline:
    """Encode every frame of a multi-camera video to tokens and decode it back.

    Args:
        tokenizer: a trained ImageTokenizer (put in eval mode by the caller).
        batch_size: frames per forward pass.
    """

    def __init__(self, tokenizer: ImageTokenizer, batch_size: int = 16):
        self.tokenizer, self.batch_size = tokenizer, batch_size

    @torch.inference_mode()
    def __call__(self, video: torch.Tensor) -> ReconstructionOutput:
        """video: (v, t, 3, H, W) float in [-1, 1]."""
        v = video.shape[0]
        frames = rearrange(video, "v t c h w -> (v t) c h w")
        device = next(self.tokenizer.parameters()).device
        tokens, recon = [], []
        for chunk in frames.split(self.batch_size):
            z = self.tokenizer.encode(chunk.to(device))
            tokens.append(z.cpu())
            recon.append(self.tokenizer.decode(z).clamp(-1, 1).cpu())
        tokens_t, recon_t = torch.cat(tokens), torch.cat(recon)
        unfold = lambda x: rearrange(x, "(v t) ... -> v t ...", v=v)  # noqa: E731
        return ReconstructionOutput(unfold(tokens_t), unfold(recon_t), unfold(psnr(recon_t, frames)), unfold(ssim(recon_t, frames)))
