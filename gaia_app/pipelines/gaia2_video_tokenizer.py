"""Inference with the GAIA-2 video tokenizer: encode clips into a latent cache, reconstruct clips.

Legend: v cameras, T frames, t = T / τ latent steps, C latent channels, H W frame size, h w latent grid.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch

from gaia_app.data.clip import Clip
from gaia_app.data.datasets import fit_to_resolution
from gaia_app.data.latent_cache import LatentClip
from gaia_app.data.transforms import resample_clip, to_float
from gaia_app.models.gaia2.video_tokenizer import VideoTokenizer
from gaia_app.nn.distributions import DiagonalGaussian

log = logging.getLogger(__name__)


def whole_steps(clip: Clip, tau: int) -> Clip:
    """The first ⌊T/τ⌋·τ frames: the tokenizer codes whole latent steps only. Dropping the tail is logged,
    and the kept frame count is stored with the latents, so nothing is lost silently."""
    keep = clip.num_frames // tau * tau
    if keep == 0:
        raise ValueError(f"clip '{clip.clip_id}': {clip.num_frames} frames, fewer than one latent step (τ={tau})")
    if keep < clip.num_frames:
        log.info("clip '%s': encoding the first %d of %d frames (whole latent steps of τ=%d)", clip.clip_id, keep,
                 clip.num_frames, tau)
        return clip.select_frames(np.arange(keep))
    return clip


@dataclass
class VideoReconstruction:
    """video: (v, T, 3, H, W) float in [-1, 1], the input at the tokenizer's size; reconstruction: same shape,
    clamped; posterior: over (1, v, t, C, h, w)."""

    video: torch.Tensor
    reconstruction: torch.Tensor
    posterior: DiagonalGaussian


class VideoTokenizerPipeline:
    """Encode (and decode) whole multi-camera clips with a trained VideoTokenizer (GAIA-2 report, tokenizer).

    Args:
        tokenizer: the trained network (put in eval mode here).
        height, width, resize_mode: the tokenizer's input size; frames are resized (and cropped) to it.
        fps: resample clips to this rate by timestamps first (None keeps the source rate).
    """

    def __init__(self, tokenizer: VideoTokenizer, height: int, width: int, resize_mode: str = "crop",
                 fps: float | None = None):
        self.tokenizer = tokenizer.eval()
        self.height, self.width, self.resize_mode, self.fps = height, width, resize_mode, fps

    @property
    def device(self) -> torch.device:
        return next(self.tokenizer.parameters()).device

    def prepare(self, clip: Clip) -> Clip:
        """Resample, resize to the tokenizer's input and cut to whole latent steps."""
        if self.fps is not None:
            clip = resample_clip(clip, self.fps)
        return whole_steps(fit_to_resolution(clip, self.height, self.width, self.resize_mode), self.tokenizer.temporal)

    @torch.inference_mode()
    def encode(self, clip: Clip) -> LatentClip:
        """clip (v, T, 3, H, W) uint8 → its posterior and every condition, ready for `write_latent_clip`."""
        clip = self.prepare(clip)
        posterior = self.tokenizer.encode(to_float(torch.from_numpy(clip.frames))[None].to(self.device))
        return LatentClip(
            clip_id=clip.clip_id, mean=posterior.mean[0].float().cpu().numpy(),
            logvar=posterior.logvar[0].float().cpu().numpy(), temporal_downsampling=self.tokenizer.temporal,
            fps=clip.fps, image_size=(self.height, self.width), timestamps=clip.timestamps, cameras=clip.cameras,
            meta=dict(clip.meta), actions=clip.actions, text=clip.text, agents=clip.agents,
            frame_meta=clip.frame_meta,
        )

    @torch.inference_mode()
    def reconstruct(self, clip: Clip) -> VideoReconstruction:
        """Encode to the posterior mean and decode: the tokenizer's reconstruction of a whole clip."""
        clip = self.prepare(clip)
        video = to_float(torch.from_numpy(clip.frames)).to(self.device)
        posterior = self.tokenizer.encode(video[None])
        reconstruction = self.tokenizer.decode(posterior.mode())[0].clamp(-1, 1)
        return VideoReconstruction(video, reconstruction, posterior)
