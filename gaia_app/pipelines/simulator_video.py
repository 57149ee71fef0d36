"""Simulator observations through the GAIA-1 video decoder (GAIA-1 §5.2), one world-model step at a time.

Legend: T' the decoder's window (frames), u the frame-rate doublings (0-2), H W the frame size.

`DecoderObserver` turns each new token frame of a closed-loop episode into video: the frame is decoded with the
frames decoded before it as context (§5.2 step 2, the autoregressive decoding, one new frame per window), then
the last few decoded frames are upsampled by the decoder's interpolation (§5.2 steps 4-5), and the 2^u frames since
the previous observation are the new observation (6.25 Hz → 25 Hz with u = 2: four frames per step). Decoding draws
from its own generator, so the world model's token sampling, and so the episode, is the same as with the
tokenizer's frame-by-frame observations.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch
from einops import repeat

from gaia_app.pipelines.gaia1_video_decoder import VideoDecodingPipeline

# base frames fed to the interpolation: enough on either side of the newest pair for a window of context
UPSAMPLE_SPAN = 4


@contextmanager
def quiet(decoder: VideoDecodingPipeline) -> Iterator[None]:
    """No progress bars from the decoder for a step's few windows."""
    shown, decoder.progress = decoder.progress, False
    try:
        yield
    finally:
        decoder.progress = shown


class DecoderObserver:
    """Decodes an episode's token frames step by step. decoder: the pipeline's VideoDecodingPipeline; upsample: u."""

    def __init__(self, decoder: VideoDecodingPipeline, upsample: int):
        if upsample not in (0, 1, 2):
            raise ValueError(f"upsample must be 0, 1 or 2 doublings, got {upsample}")
        self.decoder, self.upsample = decoder, upsample
        self.base: torch.Tensor | None = None  # (k ≤ T', 3, H, W) the latest frames decoded at the tokens' rate

    @property
    def frames_per_step(self) -> int:
        return 2**self.upsample

    @property
    def started(self) -> bool:
        """Whether this episode's first frames are decoded (`reset` ran since the last `clear`)."""
        return self.base is not None

    def clear(self) -> None:
        """Forget the episode: the next observation is a `reset`."""
        self.base = None

    @torch.no_grad()
    def reset(self, tokens: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """The episode's first token frames (t, h, w) → the observation (2^u, 3, H, W) in [-1, 1]."""
        with quiet(self.decoder):
            self.base = self.decoder.decode(tokens[None], generator)[0, -self.decoder.frames :]
            return self.recent(generator)

    @torch.no_grad()
    def step(self, tokens: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """Every token frame so far (t, h, w), the newest last → the frames since the last observation."""
        window = tokens[-self.decoder.frames :]
        n, width = window.shape[0], self.decoder.frames
        # the decoder's window always holds T' frames: pad with copies of the newest tokens (decoded, then dropped)
        padded = torch.cat([window, repeat(window[-1], "h w -> p h w", p=width - n)])[None]
        context = self.base.new_zeros(1, width, *self.base.shape[1:])
        context[0, : n - 1] = self.base[len(self.base) - (n - 1) :]
        known = torch.zeros(1, width, dtype=torch.bool, device=context.device)
        known[0, : n - 1] = True
        with quiet(self.decoder):
            new = self.decoder.window(padded, ~known, context, known, generator)[0, n - 1]
            self.base = torch.cat([self.base, new[None]])[-width:]
            return self.recent(generator)

    def recent(self, generator: torch.Generator) -> torch.Tensor:
        """The last 2^u frames of the recent base frames upsampled u times (the first frame repeated at the start
        of an episode too short to have them)."""
        video = self.base[-UPSAMPLE_SPAN:][None]
        for _ in range(self.upsample):
            video = self.decoder.upsample(video, generator)
        video = video[0]
        if len(video) < self.frames_per_step:
            video = torch.cat([repeat(video[0], "c h w -> p c h w", p=self.frames_per_step - len(video)), video])
        return video[-self.frames_per_step :]
