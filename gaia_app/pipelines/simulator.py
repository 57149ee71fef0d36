"""A closed-loop neural driving simulator over the GAIA-1 world model (GAIA-1 §9: a world model as a simulator).

Legend: T the world model's window (steps), h w the token grid, H W the frame size.

`DrivingSimulator` follows the Gymnasium `Env` API — `reset(seed=, options=)` → (observation, info),
`step(action)` → (observation, reward, terminated, truncated, info), `observation_space`, `action_space` — without
depending on gymnasium: the two spaces are small `Box`es with the same fields (`low`, `high`, `shape`, `dtype`,
`contains`, `sample`), so a policy written against Gymnasium runs unchanged, and `gymnasium.Env` can wrap it in
three lines where a user wants its wrappers. The observation is the next camera frame at the world model's rate
(6.25 Hz for the reference weights), decoded frame by frame by the tokenizer; the action is (speed m/s,
curvature 1/m), held for one step. Rewards are the user's business (0.0 here); an episode is truncated after
`max_steps`.

An episode is one open sampling session (`AutoregressiveSampler.session`): its KV cache persists across `step`
calls, so a step feeds the world model only the new frame's positions. Once the window is full (T steps), each
step slides it by one: a model with relative time (`model.net.temporal_encoding=rope`) drops the oldest step from
the cache and the slide costs nothing extra; GAIA-1's learned absolute step embeddings change when the window
slides, so such a model (the paper preset, the shipped reference weights) re-embeds and re-prefills its window on
each slide. Either way the windows, positions and conditions are those of an open-loop rollout of the same actions
(`Gaia1Pipeline.sample_batch`), so a closed-loop episode fed the actions of an open-loop rollout reproduces it token
for token (tests/test_simulator.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from einops import rearrange

from gaia_app.data.transforms import to_uint8
from gaia_app.diffusion.ar_sampling import SamplingSession
from gaia_app.diffusion.guidance import ClassifierFreeGuidance
from gaia_app.pipelines.gaia1 import Gaia1Pipeline
from gaia_app.pipelines.gaia1_inputs import (
    COMMAND_RANGES,
    DEFAULT_SPEED,
    folder_clip,
    prepare_context,
    synthetic_clip,
)
from gaia_app.pipelines.simulator_video import DecoderObserver

CONTEXTS = ("synthetic", "folder", "none")
OBSERVATIONS = ("tokenizer", "video_decoder")


@dataclass(frozen=True)
class Box:
    """A box-shaped space with Gymnasium's `spaces.Box` fields: low, high (shape), dtype."""

    low: np.ndarray
    high: np.ndarray
    dtype: type

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(self.low.shape)

    def contains(self, x: Any) -> bool:
        x = np.asarray(x)
        return x.shape == self.shape and bool(np.all(np.isfinite(x)) and np.all(x >= self.low) and np.all(x <= self.high))

    def sample(self, rng: np.random.Generator | None = None) -> np.ndarray:
        rng = rng or np.random.default_rng()
        if np.issubdtype(self.dtype, np.integer):
            return rng.integers(self.low, self.high, endpoint=True).astype(self.dtype)
        return rng.uniform(self.low, self.high).astype(self.dtype)


def action_space() -> Box:
    """(speed m/s, curvature 1/m) within the range a command may take (gaia1_inputs.COMMAND_RANGES)."""
    (speed_low, speed_high), (curv_low, curv_high) = COMMAND_RANGES["speed"], COMMAND_RANGES["curvature"]
    return Box(np.array([speed_low, curv_low], np.float32), np.array([speed_high, curv_high], np.float32), np.float32)


def checked_action(action: Any, space: Box) -> np.ndarray:
    """The action as float32 (2,), or a ValueError naming what is wrong and the accepted range."""
    try:
        value = np.asarray(action, dtype=np.float32)
    except (TypeError, ValueError):
        raise ValueError(f"action {action!r}: expected two numbers (speed m/s, curvature 1/m)") from None
    if value.shape != space.shape:
        raise ValueError(f"action of shape {value.shape}: expected {space.shape} (speed m/s, curvature 1/m)")
    if not np.all(np.isfinite(value)):
        raise ValueError(f"action {value.tolist()}: speed and curvature must be finite numbers")
    if not space.contains(value):
        raise ValueError(f"action {value.tolist()}: speed must lie in [{space.low[0]:g}, {space.high[0]:g}] m/s and "
                         f"curvature in [{space.low[1]:g}, {space.high[1]:g}] 1/m")
    return value


def episode_guidance(value: Any) -> ClassifierFreeGuidance | None | str:
    """reset option "guidance": "pipeline" (the pipeline's own), a scale ≥ 0 (GAIA-1 §5.1 eq. 3, constant over
    tokens; 0 or None: unguided) or a ClassifierFreeGuidance."""
    if value == "pipeline" or value is None or isinstance(value, ClassifierFreeGuidance):
        return value
    try:
        scale = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"reset option guidance={value!r}: expected a scale ≥ 0, None or 'pipeline'") from None
    if not np.isfinite(scale) or scale < 0:
        raise ValueError(f"reset option guidance={value!r}: expected a finite scale ≥ 0")
    return ClassifierFreeGuidance(scale) if scale > 0 else None


class DrivingSimulator:
    """Gymnasium-style closed-loop simulator (module docstring).

    Args:
        pipeline: a Gaia1Pipeline (e.g. `Gaia1Pipeline.from_weights(shipped_folder("gaia1"), video_decoder=False)`); its token
            sampler is used as it is, and its guidance unless `reset` sets the episode's.
        context_frames: real frames that start an episode (at the world model's rate).
        max_steps: steps before an episode is truncated.
        observation: "tokenizer" (each step's frame decoded on its own by the tokenizer, (H, W, 3)) or
            "video_decoder" (the pipeline's video decoder, upsampled `pipeline.upsample` times: the 2^u frames since
            the previous observation, (2^u, H, W, 3); pipelines/simulator_video.py).
    """

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(self, pipeline: Gaia1Pipeline, context_frames: int = 4, max_steps: int = 63,
                 observation: str = "tokenizer"):
        if context_frames < 1 or max_steps < 1:
            raise ValueError(f"context_frames={context_frames}, max_steps={max_steps}: expected ≥ 1 each")
        if observation not in OBSERVATIONS:
            raise ValueError(f"observation={observation!r}: expected one of {OBSERVATIONS}")
        if observation == "video_decoder" and pipeline.decoder is None:
            raise ValueError("observation='video_decoder' needs a pipeline with a video decoder (e.g. "
                             "Gaia1Pipeline.from_weights(folder, video_decoder=True))")
        self.pipeline, self.context_frames, self.max_steps = pipeline, context_frames, max_steps
        self.observer = (DecoderObserver(pipeline.decoder, pipeline.upsample) if observation == "video_decoder"
                         else None)
        shape = (*pipeline.image_size, 3) if self.observer is None else (self.observer.frames_per_step,
                                                                         *pipeline.image_size, 3)
        self.observation_space = Box(np.zeros(shape, np.uint8), np.full(shape, 255, np.uint8), np.uint8)
        self.action_space = action_space()
        self.tokens: torch.Tensor | None = None  # (steps, h, w) every frame of the episode so far
        self.session: SamplingSession | None = None  # the world model's sampling state, opened by the first step
        self.guidance: ClassifierFreeGuidance | None | str = "pipeline"  # the episode's (reset option "guidance")
        self.prompt_features: torch.Tensor | None = None  # (1, 1, m, e) the prompt, encoded once per episode
        self.actions: list[np.ndarray] = []
        self.prompt: str | None = None
        self.generator: torch.Generator | None = None
        self.decoding: torch.Generator | None = None  # the video decoder's noise
        self.steps = 0
        self.last_frame: np.ndarray | None = None

    # ---- Gymnasium API ----------------------------------------------------------------------------

    @torch.no_grad()
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Start an episode. options: context ("synthetic": clip `index` of the world `world_seed`; "folder": clip
        `index` of the clip folder `folder`; "none": the first frame is generated from `prompt` alone), prompt (a
        caption for every step, or None), guidance (classifier-free guidance scale of the episode, GAIA-1 §5.1; 0
        for none; by default the pipeline's). seed: the token sampler's noise."""
        options = dict(options or {})
        unknown = set(options) - {"context", "index", "world_seed", "folder", "prompt", "guidance"}
        if unknown:
            raise ValueError(f"reset options {sorted(unknown)}: expected context, index, world_seed, folder, prompt, "
                             "guidance")
        self.guidance = episode_guidance(options.get("guidance", "pipeline"))
        context = options.get("context", "synthetic")
        if context not in CONTEXTS:
            raise ValueError(f"reset option context={context!r}: expected one of {CONTEXTS}")
        self.prompt = options.get("prompt")
        self.prompt_features = None if self.prompt is None else self.pipeline.encode_text_batch([[self.prompt]])
        self.session = None
        seed = 0 if seed is None else int(seed)
        self.generator = torch.Generator(device=self.pipeline.device).manual_seed(seed)
        # the video decoder draws from its own generator: the token sampling stays that of tokenizer observations
        self.decoding = torch.Generator(device=self.pipeline.device).manual_seed(seed + 1)
        if self.observer is not None:
            self.observer.clear()
        self.steps = 0
        if context == "none":
            if self.prompt is None:
                raise ValueError("reset option context='none' generates the first frame from a prompt: give prompt")
            self.tokens = torch.zeros(0, *self.pipeline.token_grid, dtype=torch.long, device=self.pipeline.device)
            self.actions = []
            frame = self.advance(np.array([DEFAULT_SPEED, 0.0], np.float32))
            return frame, self.info()
        clip = (synthetic_clip(int(options.get("world_seed", 1000)), int(options.get("index", 0)),
                               *self.pipeline.image_size, (self.context_frames - 1) / self.pipeline.rate + 0.5)
                if context == "synthetic" else folder_clip(options.get("folder") or "", int(options.get("index", 0))))
        prepared = prepare_context(clip, self.context_frames, self.context_frames, self.pipeline.rate,
                                   *self.pipeline.image_size)
        self.tokens = self.pipeline.encode(prepared.frames[: self.context_frames])
        own = prepared.actions[: self.context_frames] if prepared.actions is not None else None
        self.actions = ([np.asarray(a, np.float32) for a in own] if own is not None
                        else [np.array([DEFAULT_SPEED, 0.0], np.float32)] * self.context_frames)
        self.last_frame = self.observe()
        return self.last_frame, self.info()

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        """Drive one step with `action` (speed m/s, curvature 1/m) → the next frame, reward 0.0, terminated False,
        truncated after max_steps, info (step, time_s, action, the frame's tokens)."""
        if self.tokens is None:
            raise RuntimeError("call reset() before step()")
        frame = self.advance(checked_action(action, self.action_space))
        self.steps += 1
        return frame, 0.0, False, self.steps >= self.max_steps, self.info()

    def render(self) -> np.ndarray | None:
        """The last observation (render mode "rgb_array")."""
        return self.last_frame

    def close(self) -> None:
        self.tokens, self.session = None, None

    # ---- internals --------------------------------------------------------------------------------

    @torch.no_grad()
    def advance(self, action: np.ndarray) -> np.ndarray:
        """Sample the next frame under `action`: the first step opens the sampling session on the context, later
        ones append their conditions to it (with the previous action, for the action's change)."""
        self.actions.append(action)
        rollouts = self.pipeline.rollouts
        if self.session is None:
            steps = len(self.tokens) + 1
            context = rearrange(self.tokens, "t h w -> 1 t (h w)")
            self.session = rollouts.session(context, steps, self.text(steps), self.action_steps(steps), self.generator,
                                            guidance=self.guidance)
        else:
            rollouts.extend_session(self.session, self.action_steps(2), self.text(2))
        new = rearrange(self.session.next_frame()[0], "(h w) -> h w", h=self.pipeline.token_grid[0])
        self.tokens = torch.cat([self.tokens, new[None].to(self.tokens.device)])
        self.last_frame = self.observe()
        return self.last_frame

    def action_steps(self, steps: int) -> torch.Tensor:
        """(1, steps, 2) the last `steps` actions on the world model's device."""
        return torch.from_numpy(np.stack(self.actions[-steps:]))[None].to(self.pipeline.device)

    def text(self, steps: int) -> torch.Tensor | None:
        """(1, steps, m, e) the episode's prompt at every step, or None."""
        return None if self.prompt_features is None else self.prompt_features.expand(-1, steps, -1, -1)

    def observe(self) -> np.ndarray:
        """The newest token frame as the observation: (H, W, 3) uint8 decoded by the tokenizer, or through the video
        decoder (2^u, H, W, 3), the frames since the previous observation."""
        if self.observer is None:
            frame = self.pipeline.tokenizer_frames(self.tokens[-1][None, None])[0, 0]
            return to_uint8(frame).permute(1, 2, 0).contiguous().numpy()
        frames = (self.observer.step if self.observer.started else self.observer.reset)(self.tokens, self.decoding)
        return to_uint8(frames.cpu()).permute(0, 2, 3, 1).contiguous().numpy()

    def info(self) -> dict[str, Any]:
        return {"step": self.steps, "time_s": self.steps / self.pipeline.rate,
                "action": self.actions[-1].tolist() if self.actions else None,
                "tokens": self.tokens[-1].cpu().numpy() if self.tokens is not None and len(self.tokens) else None}
