"""Sampling one window of the GAIA-1 video decoder (GAIA-1 §5.2, Fig. 4), shared by training media and
the decoding pipeline.

Legend: b batch, t frames in the window, h × w token grid, H × W image size; images in [-1, 1].
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Protocol

import torch

from gaia_app.diffusion.noise_schedule import CosineNoiseSchedule, v_from_x0, x0_from_v
from gaia_app.diffusion.samplers import Denoiser, ImageVideoBlend, standard_normal


class FrameCodec(Protocol):
    """How a decoder maps frames (b, t, 3, H, W) to what it diffuses and back (gaia_app.models.gaia1's
    ResidualFrame)."""

    def encode(self, frames: torch.Tensor) -> torch.Tensor: ...

    def decode(self, x: torch.Tensor) -> torch.Tensor: ...

    def clip(self, x: torch.Tensor) -> torch.Tensor: ...


class WindowDenoiser(Protocol):
    """What window sampling needs of a video decoder (gaia_app.models.gaia1.VideoDecoder has it): its v-prediction for
    a noised window and the frame codec of its diffused space. The sampler depends on this, not on a concrete model
    (DESIGN.md §3)."""

    def __call__(self, x_t: torch.Tensor, time: torch.Tensor, tokens: torch.Tensor, token_mask: torch.Tensor,
                 context: torch.Tensor, context_mask: torch.Tensor, temporal: bool = True,
                 rendered: torch.Tensor | None = None) -> torch.Tensor: ...

    def residual_frame(self, rendered: torch.Tensor | None, token_mask: torch.Tensor,
                       like: torch.Tensor) -> FrameCodec: ...


@torch.no_grad()
def sample_window(net: WindowDenoiser, schedule: CosineNoiseSchedule, sampler: Callable, tokens: torch.Tensor,
                  token_mask: torch.Tensor, context: torch.Tensor, context_mask: torch.Tensor,
                  blend: ImageVideoBlend | None = None, generator: torch.Generator | None = None,
                  callback: Callable | None = None, rendered: torch.Tensor | None = None) -> torch.Tensor:
    """Frames (b, t, 3, H, W) of one window, context frames copied through.

    tokens (b, t, h, w) int64; token_mask (b, t) or (b, t, h, w) bool; context (b, t, 3, H, W) clean
    frames (any values where not given); context_mask (b, t) bool. sampler: e.g. DDIMSampler.
    rendered: (b, t, 3, H, W) the tokens decoded frame by frame, for a decoder built with render_tokens.
    Context frames enter the noisy input as the forward process would noise them at every step, as in
    training, so the decoder never sees its own (never trained) guess for them.
    """
    given = context_mask[:, :, None, None, None]
    frame = net.residual_frame(rendered, token_mask, context)  # a residual decoder samples (frames − base) / scale
    clean = frame.encode(context)
    sampler, clip = pixel_clipping(sampler)

    def denoiser(temporal: bool) -> Denoiser:
        def denoise(x: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
            fresh = standard_normal(context, generator)
            x = torch.where(given, schedule.add_noise(clean, fresh, step), x)
            v = net(x, step, tokens, token_mask, clean, context_mask, temporal=temporal, rendered=rendered)
            if not clip:
                return v
            alpha, sigma = schedule.alpha_sigma(step)
            return v_from_x0(x, frame.clip(x0_from_v(x, v, alpha, sigma)), alpha, sigma)
        return denoise

    denoise = denoiser(True)
    if blend is not None:  # eq. 4: image and video denoising mixed at random steps
        denoise = blend.denoiser(denoise, denoiser(False), generator)
    noise = standard_normal(context, generator)
    frames_callback = None if callback is None else (
        lambda i, t, x, x0_pred: callback(i, t, x, frame.decode(x0_pred)))
    out = sampler(denoise, noise, generator=generator, callback=frames_callback)
    return torch.where(given, context, frame.decode(out).clamp(-1, 1))


def pixel_clipping(sampler: Callable) -> tuple[Callable, bool]:
    """(sampler without its own x̂₀ clipping, whether to clip x̂₀ in pixel space instead).

    A sampler clips x̂₀ to [−1, 1], the range of pixels; a residual decoder's variable (frames − base) / scale
    has per-pixel bounds instead, so the clip moves into the denoiser (`ResidualFrame.clip`), where it is the
    same clip for a decoder that diffuses frames."""
    if not getattr(sampler, "clip_x0", False):
        return sampler, False
    unclipped = copy.copy(sampler)
    unclipped.clip_x0 = False
    return unclipped, True
