"""A closed-loop neural driving simulator over the GAIA-1 world model (GAIA-1 §9: a world model as a simulator).

Legend: T the world model's window (steps), h w the token grid, H W the frame size.

`DrivingSimulator` is a `gymnasium.Env`, registered as "gaia_app/Drive-v0" (gaia_app/__init__.py), so
`gymnasium.make("gaia_app/Drive-v0", weights="gaia1")` builds one from a weights folder (`make_env`) and an RL
library's wrappers apply. `reset(seed=, options=)` → (observation, info); `step(action)` → (observation, reward,
terminated, truncated, info). The observation is the next camera frame at the world model's rate (6.25 Hz for the
reference weights), (H, W, 3) uint8 decoded frame by frame by the tokenizer; the action is (speed m/s, curvature
1/m) float32, held for one step. Rewards are the user's business (0.0 here); an episode is truncated after
`max_steps`, and a step after that needs a `reset` first. Everything a caller passes is checked where it enters
(pipelines/simulator_checks.py). N episodes stepped in one batched forward: pipelines/vector_simulator.py.

An episode is one open sampling session (`AutoregressiveSampler.session`, held by `EpisodeBatch` with one row):
its KV cache persists across `step` calls, so a step feeds the world model only the new frame's positions. Once
the window is full (T steps), each step slides it by one: a model with relative time
(`model.net.temporal_encoding=rope`) drops the oldest step from the cache and the slide costs nothing extra;
GAIA-1's learned absolute step embeddings change when the window slides, so such a model (the paper preset, the
shipped reference weights) re-embeds and re-prefills its window on each slide. Either way the windows, positions
and conditions are those of an open-loop rollout of the same actions (`Gaia1Pipeline.sample_batch`), so a
closed-loop episode fed the actions of an open-loop rollout reproduces it token for token (tests/test_simulator.py).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import torch
from gymnasium import spaces
from gymnasium.error import ResetNeeded

from gaia_app.data.transforms import to_uint8
from gaia_app.pipelines.gaia1 import Gaia1Pipeline
from gaia_app.pipelines.simulator_checks import action_space, checked_action, checked_options, checked_seed
from gaia_app.pipelines.simulator_episodes import EpisodeBatch
from gaia_app.pipelines.simulator_video import DecoderObserver

OBSERVATIONS = ("tokenizer", "video_decoder")
RENDER_MODES = ("rgb_array",)


class EpisodeOver(ResetNeeded, RuntimeError):
    """A step without a running episode (before the first reset, or after truncation): Gymnasium's ResetNeeded,
    and a RuntimeError for callers that catch those."""


def checked_settings(context_frames: Any, max_steps: Any, render_mode: Any) -> None:
    """The constructor's settings: context_frames and max_steps integers ≥ 1, render_mode None or "rgb_array"."""
    for name, value in (("context_frames", context_frames), ("max_steps", max_steps)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"{name}={value!r}: expected an integer ≥ 1")
    if render_mode is not None and render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode={render_mode!r}: expected None or one of {RENDER_MODES}")


def observation_box(shape: tuple[int, ...]) -> spaces.Box:
    """uint8 frames of `shape`, every value in [0, 255]."""
    return spaces.Box(0, 255, shape, dtype=np.uint8)


class DrivingSimulator(gymnasium.Env):
    """Closed-loop simulator (module docstring).

    Args:
        pipeline: a Gaia1Pipeline (e.g. `Gaia1Pipeline.from_weights(shipped_folder("gaia1"), video_decoder=False)`);
            its token sampler is used as it is, and its guidance unless `reset` sets the episode's.
        context_frames: real frames that start an episode (at the world model's rate).
        max_steps: steps before an episode is truncated.
        observation: "tokenizer" (each step's frame decoded on its own by the tokenizer, (H, W, 3)) or
            "video_decoder" (the pipeline's video decoder, upsampled `pipeline.upsample` times: the 2^u frames since
            the previous observation, (2^u, H, W, 3); pipelines/simulator_video.py).
        render_mode: None or "rgb_array" (`render` returns the newest frame (H, W, 3) either way).
    """

    metadata = {"render_modes": list(RENDER_MODES), "render_fps": 6.25}

    def __init__(self, pipeline: Gaia1Pipeline, context_frames: int = 4, max_steps: int = 63,
                 observation: str = "tokenizer", render_mode: str | None = None):
        checked_settings(context_frames, max_steps, render_mode)
        if observation not in OBSERVATIONS:
            raise ValueError(f"observation={observation!r}: expected one of {OBSERVATIONS}")
        if observation == "video_decoder" and pipeline.decoder is None:
            raise ValueError("observation='video_decoder' needs a pipeline with a video decoder (e.g. "
                             "Gaia1Pipeline.from_weights(folder, video_decoder=True))")
        self.pipeline, self.context_frames, self.max_steps = pipeline, int(context_frames), int(max_steps)
        self.render_mode = render_mode
        self.observer = (DecoderObserver(pipeline.decoder, pipeline.upsample) if observation == "video_decoder"
                         else None)
        per_step = () if self.observer is None else (self.observer.frames_per_step,)
        self.observation_space = observation_box((*per_step, *pipeline.image_size, 3))
        self.action_space = action_space()
        self.metadata = {**self.metadata, "render_fps": pipeline.rate}  # `render` gives one frame per step
        self.episodes = EpisodeBatch(pipeline, self.context_frames)
        self.decoding: torch.Generator | None = None  # the video decoder's noise
        self.steps = 0
        self.truncated = False
        self.last_frame: np.ndarray | None = None

    # ---- the episode's state, one row of `episodes` -------------------------------------------------

    @property
    def tokens(self) -> torch.Tensor | None:
        """(t, h, w) every token frame of the episode so far, or None before the first reset."""
        return None if self.episodes.tokens is None else self.episodes.tokens[0]

    @property
    def actions(self) -> list[np.ndarray]:
        """The episode's actions so far, one (2,) float32 array per step (context steps first)."""
        return [a[0] for a in self.episodes.actions]

    @property
    def session(self):
        return self.episodes.session

    @property
    def guidance(self):
        return self.episodes.guidance

    # ---- Gymnasium API ----------------------------------------------------------------------------

    @torch.no_grad()
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Start an episode. options: context ("synthetic": clip `index` of the world `world_seed`; "folder": clip
        `index` of the clip folder `folder`; "none": the first frame is generated from `prompt` alone), prompt (a
        caption for every step, or None), guidance (classifier-free guidance scale of the episode, GAIA-1 §5.1; 0
        for none; by default the pipeline's). seed: the token sampler's noise, an integer in [0, 2^63); None draws
        one from the env's generator (Gymnasium's rule: seeded by the last seeded reset)."""
        seed, settings = checked_seed(seed), checked_options(options)
        super().reset(seed=seed)
        torch_seed = int(self.np_random.integers(2**62)) if seed is None else seed
        # the video decoder draws from its own generator: the token sampling stays that of tokenizer observations
        self.decoding = torch.Generator(device=self.pipeline.device).manual_seed(torch_seed + 1)
        if self.observer is not None:
            self.observer.clear()
        self.steps, self.truncated = 0, False
        self.episodes.start(settings, [torch_seed])
        self.last_frame = self.observe()
        return self.last_frame.copy(), self.info()

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        """Drive one step with `action` (speed m/s, curvature 1/m) → the next frame, reward 0.0, terminated False,
        truncated after max_steps, info (step, time_s, action, the frame's tokens)."""
        if self.episodes.tokens is None:
            raise EpisodeOver("step() before reset(): call reset() to start an episode")
        if self.truncated:
            raise EpisodeOver(f"step() after the episode was truncated at step {self.steps} "
                              f"(max_steps={self.max_steps}): call reset() to start a new one")
        value = checked_action(action, self.action_space)
        self.episodes.advance(value[None])
        self.last_frame = self.observe()
        self.steps += 1
        self.truncated = self.steps >= self.max_steps
        return self.last_frame.copy(), 0.0, False, self.truncated, self.info()

    def render(self) -> np.ndarray | None:
        """The newest frame (H, W, 3) uint8 (render mode "rgb_array"), or None before the first reset."""
        if self.last_frame is None:
            return None
        return (self.last_frame if self.observer is None else self.last_frame[-1]).copy()

    def close(self) -> None:
        self.episodes.tokens, self.episodes.session = None, None

    # ---- internals --------------------------------------------------------------------------------

    def observe(self) -> np.ndarray:
        """The newest token frame as the observation: (H, W, 3) uint8 decoded by the tokenizer, or through the video
        decoder (2^u, H, W, 3), the frames since the previous observation."""
        if self.observer is None:
            return self.episodes.newest_frames()[0]
        frames = (self.observer.step if self.observer.started else self.observer.reset)(self.tokens, self.decoding)
        return to_uint8(frames.cpu()).permute(0, 2, 3, 1).contiguous().numpy()

    def info(self) -> dict[str, Any]:
        actions = self.episodes.actions
        return {"step": self.steps, "time_s": self.steps / self.pipeline.rate,
                "action": actions[-1][0].tolist() if actions else None,
                "tokens": (self.tokens[-1].cpu().numpy().copy() if self.tokens is not None and len(self.tokens)
                           else None)}


def load_pipeline(weights: str | Path = "gaia1", device: str = "cpu", video_decoder: bool = False) -> Gaia1Pipeline:
    """A Gaia1Pipeline from a weights folder: a shipped name ("gaia1": gaia_app/weights/gaia1) or a path."""
    from gaia_app.weights.folders import shipped_folder

    if not isinstance(weights, (str, Path)):
        raise TypeError(f"weights={weights!r}: expected a shipped weights name (e.g. 'gaia1') or a folder path")
    return Gaia1Pipeline.from_weights(shipped_folder(weights), device=device, video_decoder=video_decoder)


def make_env(weights: str | Path = "gaia1", device: str = "cpu", **kwargs: Any) -> DrivingSimulator:
    """The "gaia_app/Drive-v0" entry point: a DrivingSimulator over the weights folder `weights`. kwargs:
    DrivingSimulator's (context_frames, max_steps, observation, render_mode)."""
    video = kwargs.get("observation") == "video_decoder"
    return DrivingSimulator(load_pipeline(weights, device, video_decoder=video), **kwargs)
