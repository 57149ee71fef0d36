"""Training tasks of the GAIA-1 video decoder as frame masks (GAIA-1 §2.4, Fig. 4).

Legend:
    t frames in a window (T' = 7 in the paper), h × w token grid.

Every task is one video window with two per-frame masks: which frames are given as clean context
images, and which frames get their image tokens. The decoder is asked for the remaining frames and
the loss covers exactly those. `temporal` says whether the temporal layers run (image generation
trains the decoder with them off, GAIA-1 §2.4).

| task | context frames | tokens | temporal |
|---|---|---|---|
| image | none | every frame | off |
| video | none | every frame | on |
| forward | the first `context` frames | the others | on |
| backward | the last `context` frames | the others | on |
| interpolation | every other frame (0, 2, 4, …) | none | on |

Interpolation puts the context at both ends of every gap because that is how it is used: temporal
upsampling (GAIA-1 §5.2 steps 4-5) doubles the frame rate by filling the frame between each pair.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

TASKS = ("image", "video", "forward", "backward", "interpolation")


@dataclass(frozen=True)
class DecoderTask:
    """Masks of one task: context (t,) bool, tokens (t,) bool; target = frames that are not context."""

    name: str
    context: torch.Tensor
    tokens: torch.Tensor
    temporal: bool

    @property
    def target(self) -> torch.Tensor:
        """(t,) bool: the frames the decoder generates and the loss covers."""
        return ~self.context


def make_task(name: str, frames: int, context: int = 2) -> DecoderTask:
    """The Fig. 4 masks of task `name` for a window of `frames` frames; `context` frames for the AR tasks."""
    if name not in TASKS:
        raise ValueError(f"unknown video-decoder task {name!r}, expected one of {TASKS}")
    if name in ("forward", "backward") and not 0 < context < frames:
        raise ValueError(f"autoregressive decoding needs 0 < context < frames, got context={context}, frames={frames}")
    if name == "interpolation" and frames < 3:
        raise ValueError(f"interpolation needs ≥ 3 frames (context, gap, context), got {frames}")
    index = torch.arange(frames)
    given = {
        "image": torch.zeros(frames, dtype=torch.bool),
        "video": torch.zeros(frames, dtype=torch.bool),
        "forward": index < context,
        "backward": index >= frames - context,
        "interpolation": index % 2 == 0,
    }[name]
    tokens = torch.zeros(frames, dtype=torch.bool) if name == "interpolation" else ~given
    return DecoderTask(name, given, tokens, temporal=name != "image")


class TaskSampler:
    """Draws a task per batch with the given probabilities (GAIA-1 §4.3: all equal).

    Args:
        probabilities: {task: weight} over TASKS (normalised; missing tasks get 0).
        frames: T'. context: past/future frames given to the autoregressive tasks (§5.2 decodes with 2).
    """

    def __init__(self, probabilities: dict[str, float], frames: int, context: int = 2):
        unknown = set(probabilities) - set(TASKS)
        if unknown or min(probabilities.values(), default=0) < 0 or sum(probabilities.values()) <= 0:
            raise ValueError(f"task probabilities need non-negative weights over {TASKS}, got {probabilities}")
        self.tasks = [make_task(name, frames, context) for name in TASKS]
        weights = torch.tensor([float(probabilities.get(name, 0.0)) for name in TASKS])
        self.probs = weights / weights.sum()

    def __call__(self, generator: torch.Generator | None = None) -> DecoderTask:
        return self.tasks[int(torch.multinomial(self.probs, 1, generator=generator))]


def drop_tokens(mask: torch.Tensor, rate: float, generator: torch.Generator | None = None) -> torch.Tensor:
    """Token conditioning dropout (GAIA-1 §2.4, p = 0.15): each token kept with probability 1 − rate.

    mask: (b, t, h, w) bool, True where a token is given → the same with dropped tokens set False.
    """
    keep = torch.rand(mask.shape, generator=generator, device=mask.device) >= rate
    return mask & keep
