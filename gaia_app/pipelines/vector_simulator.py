"""N closed-loop episodes of the GAIA-1 world model in one batched forward (GAIA-1 §9), as a Gymnasium VectorEnv.

Legend: N sub-episodes (`num_envs`), h w the token grid, H W the frame size.

`VectorDrivingSimulator` steps N episodes through one sampling session of batch N (`EpisodeBatch`,
pipelines/simulator_episodes.py): each image token of a step is one forward of the world model for all N, where N
single `DrivingSimulator`s would make N. Each episode draws its tokens with its own generator, so sub-episode i
reset with seed s and fed the same actions is the episode a single env reset with seed s gives, up to float
rounding: the batched forward's logits differ from a batch of one's by ~4e-6, which now and then moves a sampled
token across a boundary (1 of 8 episodes in 24 steps in benchmarks/bench_vector_simulator.py), and the episode
goes on as another sample of the same distribution. With greedy picking they are equal token for token
(tests/test_vector_simulator.py).
`gymnasium.make_vec("gaia_app/Drive-v0", num_envs=N)` builds one from a weights folder (`make_vector_env`).

All N episodes start together and are truncated together after `max_steps`; the step after that resets them all
(Gymnasium's next-step autoreset: that step's actions are ignored, the observations are the new episodes' first
frames, rewards 0). Observations come from the tokenizer (the video decoder's are single-env only).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from gaia_app.pipelines.gaia1 import Gaia1Pipeline
from gaia_app.pipelines.simulator import (
    RENDER_MODES,
    EpisodeOver,
    checked_settings,
    load_pipeline,
    observation_box,
)
from gaia_app.pipelines.simulator_checks import (
    SEED_LIMIT,
    EpisodeOptions,
    action_space,
    checked_action,
    checked_integer,
    checked_options,
    checked_seed,
)
from gaia_app.pipelines.simulator_episodes import EpisodeBatch

MAX_ENVS = 1024  # a batch beyond this is a typo rather than a plan (memory grows with N × window)


class VectorDrivingSimulator(VectorEnv):
    """N closed-loop episodes stepped by one batched world model (module docstring).

    Args:
        pipeline: a Gaia1Pipeline; its sampler settings and guidance are used as they are.
        num_envs: N, the episodes stepped together.
        context_frames, max_steps, render_mode: as DrivingSimulator's (every sub-episode alike).
        observation: "tokenizer" only (the video decoder's observations: DrivingSimulator).
    """

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": list(RENDER_MODES), "render_fps": 6.25}

    def __init__(self, pipeline: Gaia1Pipeline, num_envs: int = 1, context_frames: int = 4, max_steps: int = 63,
                 render_mode: str | None = None, observation: str = "tokenizer"):
        checked_settings(context_frames, max_steps, render_mode)
        self.num_envs = checked_integer(num_envs, "num_envs", 1, MAX_ENVS + 1)
        if observation != "tokenizer":
            raise ValueError(f"observation={observation!r}: the vector env observes through the tokenizer only "
                             "(expected 'tokenizer'; DrivingSimulator has 'video_decoder')")
        self.pipeline, self.max_steps, self.render_mode = pipeline, int(max_steps), render_mode
        self.metadata = {**self.metadata, "render_fps": pipeline.rate}
        self.single_observation_space = observation_box((*pipeline.image_size, 3))
        self.single_action_space = action_space()
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.episodes = EpisodeBatch(pipeline, int(context_frames))
        self.settings = EpisodeOptions(indices=(0,) * self.num_envs)
        self.steps, self.truncated = 0, False
        self.frames: np.ndarray | None = None  # (N, H, W, 3) the newest observations

    def reset(self, *, seed: int | list[int | None] | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Start N episodes. seed: an integer s (episode i gets s + i), N seeds (None entries drawn from the env's
        generator, which the first seed seeds) or None (all drawn); options: DrivingSimulator.reset's, with `index`
        one clip index for all or N of them. → observations (N, H, W, 3) uint8 and infos (Gymnasium's vector
        layout)."""
        seeds, self.settings = self.row_seeds(seed), checked_options(options, self.num_envs)
        super().reset(seed=seeds[0])  # the env's own generator (drawn seeds, autoresets) follows the first seed
        return self.start([int(self.np_random.integers(2**62)) if s is None else s for s in seeds])

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """actions (N, 2) (speed m/s, curvature 1/m) → observations (N, H, W, 3), rewards (N,) 0.0, terminations
        (N,) False, truncations (N,) (after max_steps), infos. The step after truncation resets every episode."""
        if self.episodes.tokens is None:
            raise EpisodeOver("step() before reset(): call reset() to start the episodes")
        value = checked_action(actions, self.action_space, "actions")
        if self.truncated:  # next-step autoreset: the same options, new seeds from the env's generator
            observations, infos = self.start([int(s) for s in self.np_random.integers(2**62, size=self.num_envs)])
            return observations, np.zeros(self.num_envs), *self.flags(False), infos
        self.episodes.advance(value)
        self.steps += 1
        self.truncated = self.steps >= self.max_steps
        self.frames = self.episodes.newest_frames()
        return self.frames.copy(), np.zeros(self.num_envs), *self.flags(self.truncated), self.infos()

    def render(self) -> tuple[np.ndarray, ...] | None:
        """The newest frame of every episode, N arrays (H, W, 3) uint8, or None before the first reset."""
        return None if self.frames is None else tuple(frame.copy() for frame in self.frames)

    def close_extras(self, **kwargs: Any) -> None:
        self.episodes.tokens, self.episodes.session = None, None

    # ---- internals --------------------------------------------------------------------------------

    def row_seeds(self, seed: Any) -> list[int | None]:
        """reset's seed → one seed (or None: drawn) per episode."""
        if seed is None:
            return [None] * self.num_envs
        if isinstance(seed, (list, tuple)) and len(seed) == self.num_envs:
            return [checked_seed(s, f"seed[{i}]") for i, s in enumerate(seed)]
        if isinstance(seed, (list, tuple)):
            raise ValueError(f"seed={seed!r}: expected one integer or {self.num_envs} (one per sub-episode)")
        first = checked_seed(seed)
        if first + self.num_envs > SEED_LIMIT:
            raise ValueError(f"seed={seed}: episode i gets seed + i, so expected an integer in "
                             f"[0, {SEED_LIMIT - self.num_envs}] for num_envs={self.num_envs}")
        return [first + i for i in range(self.num_envs)]

    @torch.no_grad()
    def start(self, seeds: list[int]) -> tuple[np.ndarray, dict[str, Any]]:
        """Open every episode with the current settings and `seeds`."""
        self.episodes.start(self.settings, seeds)
        self.steps, self.truncated = 0, False
        self.frames = self.episodes.newest_frames()
        return self.frames.copy(), self.infos()

    def flags(self, truncated: bool) -> tuple[np.ndarray, np.ndarray]:
        """(terminations, truncations), each (N,) bool."""
        return np.zeros(self.num_envs, bool), np.full(self.num_envs, truncated)

    def infos(self) -> dict[str, Any]:
        """step, time_s, the last action (N, 2) and the newest tokens (N, h, w), with Gymnasium's `_key` masks."""
        infos: dict[str, Any] = {}
        tokens = self.episodes.tokens[:, -1].cpu().numpy()
        for i in range(self.num_envs):
            info = {"step": self.steps, "time_s": self.steps / self.pipeline.rate,
                    "action": self.episodes.actions[-1][i].copy() if self.episodes.actions else np.full(2, np.nan),
                    "tokens": tokens[i].copy()}
            infos = self._add_info(infos, info, i)
        return infos


def make_vector_env(num_envs: int = 1, weights: str | Path = "gaia1", device: str = "cpu",
                    **kwargs: Any) -> VectorDrivingSimulator:
    """The "gaia_app/Drive-v0" vector entry point (`gymnasium.make_vec(..., num_envs=N)`): N episodes over the
    weights folder `weights`. kwargs: VectorDrivingSimulator's (context_frames, max_steps, render_mode)."""
    return VectorDrivingSimulator(load_pipeline(weights, device), num_envs, **kwargs)
