"""GAIA-1 video decoding: image tokens → video at 6.25, 12.5 and 25 Hz (GAIA-1 §5.2).

Legend:
    b batch, N frames at 6.25 Hz, t frames in one decoder window (≤ T'), h × w token grid,
    H × W image size; images in [-1, 1].

Procedure (§5.2): decode the last T' frames from their tokens; decode backwards T' − 2 frames at a
time with the 2 following frames as context (the paper found backwards gives more stable objects and
less flicker on the horizon; forwards is available); then double the frame rate twice with the
interpolation task (N → 2N − 1 → 4N − 3 frames). Every window is sampled with DDIM (or any sampler of
`gaia_app.diffusion.samplers`), optionally blending image and video denoising (eq. 4).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import torch
from tqdm.auto import tqdm

from gaia_app.diffusion.noise_schedule import CosineNoiseSchedule
from gaia_app.diffusion.samplers import ImageVideoBlend
from gaia_app.diffusion.video_sampling import sample_window
from gaia_app.models.gaia1.video_decoder import VideoDecoder
from gaia_app.utils import threads


@dataclass
class DecodedVideo:
    """frames at 6.25 Hz (b, N, 3, H, W), 12.5 Hz (b, 2N − 1, …) and 25 Hz (b, 4N − 3, …); None when skipped."""

    base: torch.Tensor
    double: torch.Tensor | None = None
    quadruple: torch.Tensor | None = None


def backward_windows(n: int, frames: int, context: int) -> list[tuple[int, int]]:
    """[start, stop) windows decoding n frames backwards: the last `frames`, then `frames − context`
    new ones at a time, each window ending with `context` frames decoded before (GAIA-1 §5.2 steps 1-3)."""
    start = max(0, n - frames)
    windows = [(start, n)]
    while start > 0:
        new_start = max(0, start - (frames - context))
        windows.append((new_start, start + context))
        start = new_start
    return windows


def full_length(windows: list[tuple[int, int]], n: int, frames: int) -> list[tuple[int, int]]:
    """Each window widened to `frames` (when n ≥ frames) over frames decoded before it: the last backward window
    (or forward one) would otherwise be shorter than T' and show the decoder temporal positions it was never
    trained to generate at; the extra frames become context."""
    widened = []
    for start, stop in windows:
        if stop - start < frames <= n:
            start, stop = (0, frames) if start == 0 else (stop - frames, stop)
        widened.append((start, stop))
    return widened


def forward_windows(n: int, frames: int, context: int) -> list[tuple[int, int]]:
    """The mirror image of `backward_windows`: the first `frames`, then onwards with `context` past frames."""
    return [(n - stop, n - start) for start, stop in backward_windows(n, frames, context)]


def interpolation_windows(n_out: int, frames: int) -> list[tuple[int, int]]:
    """Windows over the 2N − 1 upsampled frames, known frames at even indices: each window starts and
    ends on a known frame and has odd length ≤ frames, consecutive windows share one known frame."""
    span = frames - 1 if frames % 2 else frames - 2  # even, so both ends are known frames
    return [(start, min(start + span, n_out - 1) + 1) for start in range(0, n_out - 1, span)]


class VideoDecodingPipeline:
    """Decode token sequences of any length into videos with a trained VideoDecoder (GAIA-1 §5.2).

    Args:
        net: the (EMA) decoder. schedule: its noise schedule. sampler: e.g. DDIMSampler(schedule, 50).
        frames: T'. context: overlapping context frames of the autoregressive steps (2 in the paper).
        blend: eq. 4 image/video blend (p = 0.25, w = 0.5 in the paper), or None.
        backward: decode from the end of the sequence (the paper's choice) or from the start.
        progress: a progress bar over windows.
        render_tokens: tokens (b, t, h, w) → the tokenizer's frame-by-frame decoding (b, t, 3, H, W); required
            by a decoder built with render_tokens (e.g. `VideoDecoderModule.render_tokens`).
    """

    def __init__(self, net: VideoDecoder, schedule: CosineNoiseSchedule, sampler: Callable, frames: int = 7,
                 context: int = 2, blend: ImageVideoBlend | None = None, backward: bool = True, progress: bool = False,
                 render_tokens: Callable[[torch.Tensor], torch.Tensor] | None = None):
        if not 0 < context < frames:
            raise ValueError(f"context frames must be in 1..{frames - 1}, got {context}")
        if getattr(net, "render_tokens", False) and render_tokens is None:
            raise ValueError("this video decoder was trained with render_tokens=True: pass render_tokens= (the "
                             "tokenizer's frame-by-frame decoding, e.g. VideoDecoderModule.render_tokens)")
        self.render_tokens = render_tokens if getattr(net, "render_tokens", False) else None
        self.net, self.schedule, self.sampler = net, schedule, sampler
        self.frames, self.context, self.blend = frames, context, blend
        self.backward, self.progress = backward, progress

    def window(self, tokens: torch.Tensor, token_mask: torch.Tensor, context: torch.Tensor, context_mask: torch.Tensor,
               generator: torch.Generator | None = None) -> torch.Tensor:
        """One window with this pipeline's sampler and blend (see `sample_window`)."""
        threads.tick()  # follow the load other processes put on the CPUs (gaia_app/utils/threads.py)
        rendered = self.render_tokens(tokens) if self.render_tokens is not None else None
        return sample_window(self.net, self.schedule, self.sampler, tokens, token_mask, context, context_mask,
                             self.blend, generator, rendered=rendered)

    def decode(self, tokens: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """tokens (b, N, h, w) → frames (b, N, 3, H, W) at the tokens' rate (GAIA-1 §5.2 steps 1-3).

        Every window holds T' frames: a sequence shorter than T' is padded with copies of its last frame's tokens
        (decoded, then dropped), and the last window is widened over frames decoded before (`full_length`)."""
        n = tokens.shape[1]
        if n < self.frames:
            padding = tokens[:, -1:].expand(-1, self.frames - n, -1, -1)
            return self.decode(torch.cat([tokens, padding], dim=1), generator)[:, :n]
        b = tokens.shape[0]
        height, width = self.net.image_size
        frames = tokens.new_zeros(b, n, 3, height, width, dtype=torch.float32)
        done = torch.zeros(n, dtype=torch.bool)
        order = backward_windows if self.backward else forward_windows
        windows = full_length(order(n, self.frames, self.context), n, self.frames)
        with self.bar(windows, "decode") as bar:
            for start, stop in bar:
                context_mask = done[start:stop].to(tokens.device).expand(b, -1)
                frames[:, start:stop] = self.window(tokens[:, start:stop], ~context_mask, frames[:, start:stop],
                                                    context_mask, generator)
                done[start:stop] = True
        return frames

    @contextmanager
    def bar(self, windows: list[tuple[int, int]], desc: str) -> Iterator[tqdm]:
        """A progress bar over windows whose text also counts the decoder's forward passes inside the current
        window: a window of 50 DDIM steps takes minutes on a CPU, and a bar standing at 0/2 for that long cannot be
        told from a hung run."""
        bar = tqdm(windows, desc=desc, disable=not self.progress)
        calls = [0]

        def count(*_: object) -> None:
            calls[0] += 1
            bar.set_postfix_str(f"decoder pass {calls[0]}", refresh=True)

        handle = self.net.register_forward_hook(count) if self.progress else None
        try:
            yield bar
        finally:
            if handle is not None:
                handle.remove()
            bar.close()

    def upsample(self, frames: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """Double the frame rate by interpolation (GAIA-1 §5.2 steps 4-5): (b, N, …) → (b, 2N − 1, …)."""
        b, n = frames.shape[:2]
        out = frames.new_zeros(b, 2 * n - 1, *frames.shape[2:])
        out[:, ::2] = frames
        known = (torch.arange(2 * n - 1) % 2 == 0).to(frames.device)
        h, w = self.net.token_grid
        with self.bar(interpolation_windows(2 * n - 1, self.frames), "upsample") as bar:
            for start, stop in bar:
                t = stop - start
                no_tokens = torch.zeros(b, t, h, w, dtype=torch.long, device=frames.device)
                mask = known[start:stop].expand(b, -1)
                out[:, start:stop] = self.window(no_tokens, torch.zeros_like(mask), out[:, start:stop], mask,
                                                 generator)
        return out

    def __call__(self, tokens: torch.Tensor, upsample: int = 2,
                 generator: torch.Generator | None = None) -> DecodedVideo:
        """tokens (b, N, h, w) → DecodedVideo; `upsample` doublings of the frame rate (0, 1 or 2)."""
        if upsample not in (0, 1, 2):
            raise ValueError(f"upsample must be 0, 1 or 2 doublings (6.25 → 12.5 → 25 Hz), got {upsample}")
        video = DecodedVideo(self.decode(tokens, generator))
        if upsample >= 1:
            video.double = self.upsample(video.base, generator)
        if upsample == 2:
            video.quadruple = self.upsample(video.double, generator)
        return video
