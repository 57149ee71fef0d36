"""b closed-loop episodes of the GAIA-1 world model stepped together (GAIA-1 §9: a world model as a simulator).

Legend: b episodes, t steps so far, t0 context steps, h w the token grid, n = h·w, H W the frame size.

`EpisodeBatch` is the state both simulators share: `DrivingSimulator` (pipelines/simulator.py) holds one with
b = 1, `VectorDrivingSimulator` (pipelines/vector_simulator.py) one with b = N. All b episodes live in one sampling
session (`WorldModelRolloutPipeline.session`, its KV cache kept across steps), so a step is one batched forward per
image token for all of them. Each episode keeps its own token generator: `RowwisePicker` draws row i's token
with generator i exactly as a batch-1 session seeded alike would, so an episode's draws do not depend on which
other episodes share its batch (its logits do, in the last float bits: pipelines/vector_simulator.py).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from einops import rearrange, repeat

from gaia_app.data.transforms import to_uint8
from gaia_app.diffusion.ar_sampling import AutoregressiveSampler, SamplingSession, TokenPicker
from gaia_app.diffusion.guidance import ClassifierFreeGuidance
from gaia_app.pipelines.gaia1 import Gaia1Pipeline
from gaia_app.pipelines.gaia1_inputs import DEFAULT_SPEED, folder_clip, prepare_context, synthetic_clip
from gaia_app.pipelines.gaia1_world_model import WorldModelRolloutPipeline
from gaia_app.pipelines.simulator_checks import EpisodeOptions


@dataclass(frozen=True)
class RowwisePicker:
    """The pipeline's token picker applied row by row, each row with its own generator.

    The sampling session hands its `generator` to the picker untouched; here it is a sequence of b generators.
    Row i's call is the very call a batch-1 session makes (`picker(logits (1, V), generator_i)`), so an episode
    samples the same tokens from the same logits whatever its batch."""

    picker: TokenPicker

    def __call__(self, logits: torch.Tensor, generators: Sequence[torch.Generator],
                 gumbel: torch.Tensor | None = None) -> torch.Tensor:
        """(b, V) logits and b generators → (b,) int64 tokens."""
        if gumbel is not None or len(generators) != logits.shape[0]:
            raise ValueError(f"RowwisePicker: expected one generator per row ({logits.shape[0]}) and no shared noise; "
                             f"got {len(generators)} generators")
        return torch.cat([self.picker(logits[i : i + 1], g) for i, g in enumerate(generators)])


def rowwise_rollouts(pipeline: Gaia1Pipeline) -> WorldModelRolloutPipeline:
    """The pipeline's rollouts (net, cache and decode-step settings, guidance, guided streams) with a
    `RowwisePicker`."""
    rollouts = pipeline.rollouts
    base = rollouts.sampler
    sampler = AutoregressiveSampler(RowwisePicker(base.picker), base.use_cache, decode_step=base.decode_step,
                                    cache_capacity=base.cache_capacity, tokens_per_call=base.tokens_per_call)
    return WorldModelRolloutPipeline(rollouts.net, sampler, rollouts.guidance, rollouts.guided_streams)


class EpisodeBatch:
    """b episodes advanced one step at a time by one batched sampling session.

    Args:
        pipeline: a Gaia1Pipeline; its world model, sampler settings and guidance are used as they are.
        context_frames: real frames that start an episode (at the world model's rate).
    """

    def __init__(self, pipeline: Gaia1Pipeline, context_frames: int):
        self.pipeline, self.context_frames = pipeline, context_frames
        self.rollouts = rowwise_rollouts(pipeline)
        self.tokens: torch.Tensor | None = None  # (b, t, h, w) every frame of the episodes so far
        self.actions: list[np.ndarray] = []  # t arrays (b, 2): (speed m/s, curvature 1/m) per step
        self.session: SamplingSession | None = None  # opened by the first step
        self.guidance: ClassifierFreeGuidance | None | str = "pipeline"
        self.prompt_features: torch.Tensor | None = None  # (b, 1, m, e) the prompt, encoded once per episode
        self.generators: tuple[torch.Generator, ...] = ()

    @property
    def size(self) -> int:
        return len(self.generators)

    @torch.no_grad()
    def start(self, options: EpisodeOptions, seeds: Sequence[int]) -> None:
        """Open len(seeds) episodes: seed i drives episode i's token draws; options.indices picks each one's clip."""
        device = self.pipeline.device
        self.generators = tuple(torch.Generator(device=device).manual_seed(s) for s in seeds)
        self.guidance, self.session = options.guidance, None
        self.prompt_features = None if options.prompt is None else repeat(
            self.pipeline.encode_text_batch([[options.prompt]]), "1 t m e -> b t m e", b=self.size)
        if options.context == "none":  # the first frame comes from the prompt alone
            self.tokens = torch.zeros(self.size, 0, *self.pipeline.token_grid, dtype=torch.long, device=device)
            self.actions = []
            self.advance(np.tile(np.array([DEFAULT_SPEED, 0.0], np.float32), (self.size, 1)))
            return
        contexts = {i: self.context(options, i) for i in sorted(set(options.indices))}  # each clip encoded once
        self.tokens = torch.stack([contexts[i][0] for i in options.indices])
        self.actions = list(np.stack([contexts[i][1] for i in options.indices], axis=1))

    def context(self, options: EpisodeOptions, index: int) -> tuple[torch.Tensor, np.ndarray]:
        """Clip `index` of the options' context → its tokens (t0, h, w) and actions (t0, 2) (the default speed,
        straight, for a clip without actions)."""
        seconds = (self.context_frames - 1) / self.pipeline.rate + 0.5
        clip = (synthetic_clip(options.world_seed, index, *self.pipeline.image_size, seconds)
                if options.context == "synthetic" else folder_clip(options.folder, index))
        prepared = prepare_context(clip, self.context_frames, self.context_frames, self.pipeline.rate,
                                   *self.pipeline.image_size)
        tokens = self.pipeline.encode(prepared.frames[: self.context_frames])
        if prepared.actions is None:
            return tokens, np.tile(np.array([DEFAULT_SPEED, 0.0], np.float32), (self.context_frames, 1))
        return tokens, np.asarray(prepared.actions[: self.context_frames], np.float32)

    @torch.no_grad()
    def advance(self, actions: np.ndarray) -> torch.Tensor:
        """Sample every episode's next frame under actions (b, 2) → its tokens (b, h, w). The first step opens the
        session on the context; later ones append their conditions (with the previous action, for its change)."""
        self.actions.append(np.asarray(actions, np.float32))
        if self.session is None:
            steps = self.tokens.shape[1] + 1
            context = rearrange(self.tokens, "b t h w -> b t (h w)")
            self.session = self.rollouts.session(context, steps, self.text(steps), self.action_steps(steps),
                                                 self.generators, guidance=self.guidance)
        else:
            self.rollouts.extend_session(self.session, self.action_steps(2), self.text(2))
        new = rearrange(self.session.next_frame(), "b (h w) -> b h w", h=self.pipeline.token_grid[0])
        self.tokens = torch.cat([self.tokens, new[:, None].to(self.tokens.device)], dim=1)
        return new

    def action_steps(self, steps: int) -> torch.Tensor:
        """(b, steps, 2) the last `steps` actions on the world model's device."""
        return torch.from_numpy(np.stack(self.actions[-steps:], axis=1)).to(self.pipeline.device)

    def text(self, steps: int) -> torch.Tensor | None:
        """(b, steps, m, e) the episodes' prompt at every step, or None."""
        return None if self.prompt_features is None else self.prompt_features.expand(-1, steps, -1, -1)

    @torch.no_grad()
    def newest_frames(self) -> np.ndarray:
        """The newest token frame of every episode decoded by the tokenizer: (b, H, W, 3) uint8."""
        frames = self.pipeline.tokenizer_frames(self.tokens[:, -1:])[:, 0]
        return to_uint8(frames).permute(0, 2, 3, 1).contiguous().numpy()
