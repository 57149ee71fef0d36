"""Inference with the GAIA-1 image tokenizer (GAIA-1 §2.2): video → tokens → reconstruction, and
clip → token segments for the world model's token cache."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from einops import rearrange

from gaia_app.data.clip import Clip
from gaia_app.data.datasets import fit_to_resolution
from gaia_app.data.names import check_camera_name
from gaia_app.data.token_cache import TokenSegment
from gaia_app.data.transforms import resample_clip, to_float
from gaia_app.eval.metrics import psnr, ssim
from gaia_app.models.tokenizer_protocol import DiscreteTokenizer


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
        tokenizer: a trained tokenizer (DiscreteTokenizer; put in eval mode by the caller).
        batch_size: frames per forward pass.
    """

    def __init__(self, tokenizer: DiscreteTokenizer, batch_size: int = 16):
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
        return ReconstructionOutput(unfold(tokens_t), unfold(recon_t), unfold(psnr(recon_t, frames)),
                                    unfold(ssim(recon_t, frames)))


def camera_names(clip: Clip) -> list[str]:
    """One plain name per view (gaia_app/data/names.py): the camera specs', else meta["camera_names"], else view0,
    view1, … They become parts of output file names, so each is checked."""
    names = [c.name for c in clip.cameras] if clip.cameras else \
        list(clip.meta.get("camera_names", [f"view{v}" for v in range(clip.num_views)]))
    return [check_camera_name(name, f"clip '{clip.clip_id}'") for name in names]


def segment_names(clip: Clip) -> list[str]:
    """Token-cache segment names of a clip, one per camera: `<clip_id>/<camera>` (a folder per clip, so no two
    clips' cameras can share a file name)."""
    return [f"{clip.clip_id}/{camera}" for camera in camera_names(clip)]


@dataclass
class TokenizedClip:
    """segments: one TokenSegment per camera, tokens (t, h, w) int64 with the clip's
    timestamps (t,), actions (t, 2) and captions (t) where the clip has them."""

    segments: list[TokenSegment]


class TokenCachePipeline:
    """Encode every frame of every camera of a clip once, for world-model training on tokens (GAIA-1 §2.2–2.3).

    Args:
        tokenizer: a trained tokenizer (DiscreteTokenizer; put in eval mode by the caller).
        height, width, resize_mode: the tokenizer's input size; frames are resized (and cropped) to it.
        fps: resample the clip to this rate by timestamps first (None keeps the source rate).
        batch_size: frames per forward pass.
    """

    def __init__(self, tokenizer: DiscreteTokenizer, height: int, width: int, resize_mode: str = "crop",
                 fps: float | None = None, batch_size: int = 16):
        self.tokenizer, self.height, self.width, self.resize_mode = tokenizer, height, width, resize_mode
        self.fps, self.batch_size = fps, batch_size

    @torch.inference_mode()
    def __call__(self, clip: Clip) -> TokenizedClip:
        """clip: frames (v, t, 3, H, W) uint8 → one (t, h, w) token segment per camera."""
        if self.fps is not None:
            clip = resample_clip(clip, self.fps)
        clip = fit_to_resolution(clip, self.height, self.width, self.resize_mode)
        frames = rearrange(torch.from_numpy(clip.frames), "v t c h w -> (v t) c h w")
        device = next(self.tokenizer.parameters()).device
        # uint8 → float per chunk: a long clip never sits in memory as float
        tokens = torch.cat([self.tokenizer.encode(to_float(chunk).to(device)).cpu()
                            for chunk in frames.split(self.batch_size)])
        tokens = rearrange(tokens, "(v t) h w -> v t h w", v=clip.num_views).numpy()
        return TokenizedClip([TokenSegment(name, tokens[v], clip.actions, clip.timestamps, clip.text)
                              for v, name in enumerate(segment_names(clip))])
