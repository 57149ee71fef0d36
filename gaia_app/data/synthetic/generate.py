"""Generate synthetic clips: plan → simulate → label → render → `Clip`.

`generate_clip(seed, ...)` returns a `Clip`; `generate_sample(...)` also keeps the simulated
world so instance masks can be rendered on demand. Everything is drawn from one
`np.random.Generator` seeded by the caller: no global random state is read or changed.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from gaia_app.data.clip import Clip
from gaia_app.data.synthetic.appearance import make_appearance
from gaia_app.data.synthetic.captions import Captioner
from gaia_app.data.synthetic.labels import LABEL_RANGE, agent_boxes, frame_meta
from gaia_app.data.synthetic.planning import ScenePlan, make_plan
from gaia_app.data.synthetic.rig import build_rig, resolve_camera_names
from gaia_app.data.synthetic.scenario import TIMES_OF_DAY, WEATHERS, Scenario, draw_setting
from gaia_app.data.synthetic.scene import ClipRenderer
from gaia_app.data.synthetic.simulate import FrameState, simulate
from gaia_app.data.transforms import resample_indices

DEFAULT_WEATHER_MIX = {"clear": 0.55, "rain": 0.15, "fog": 0.15, "snow": 0.15}
DEFAULT_TIME_OF_DAY_MIX = {"day": 0.6, "dusk": 0.2, "night": 0.2}


def _check_mix(name: str, mix: Mapping[str, float] | None, allowed: tuple[str, ...], default: dict) -> dict[str, float]:
    if mix is None:
        return dict(default)
    if not isinstance(mix, Mapping):
        raise ValueError(f"{name}: expected a mapping of probabilities over {allowed}, got {mix!r}")
    out = {str(k): float(v) for k, v in mix.items()}
    unknown = sorted(set(out) - set(allowed))
    if unknown or not out or any(v < 0 for v in out.values()) or sum(out.values()) <= 0:
        raise ValueError(f"{name}: expected non-negative probabilities over {allowed} with a positive sum, "
                         f"got {dict(mix)}")
    return out


@dataclass(frozen=True)
class WorldConfig:
    """Validated knobs of the synthetic world (see generate_clip for their meaning)."""

    height: int = 64
    width: int = 112
    cameras: tuple[str, ...] = ("front",)
    clip_len: int = 8
    fps: float = 25.0
    weather_mix: dict[str, float] = field(default_factory=lambda: dict(DEFAULT_WEATHER_MIX))
    time_of_day_mix: dict[str, float] = field(default_factory=lambda: dict(DEFAULT_TIME_OF_DAY_MIX))
    agent_density: float = 1.0

    @classmethod
    def make(cls, height: int = 64, width: int = 112, cameras: int | Sequence[str] = ("front",), clip_len: int = 8,
             fps: float = 25.0, weather_mix: Mapping[str, float] | None = None,
             time_of_day_mix: Mapping[str, float] | None = None, agent_density: float = 1.0) -> "WorldConfig":
        """Validate the knobs; raise ValueError naming the argument and what was expected."""
        for name, value, low in (("height", height, 16), ("width", width, 16), ("clip_len", clip_len, 1)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
                raise ValueError(f"{name}: expected an integer >= {low}, got {value!r}")
        if not np.isfinite(fps) or fps <= 0:
            raise ValueError(f"fps: expected a positive frame rate in Hz, got {fps!r}")
        if not np.isfinite(agent_density) or agent_density < 0:
            raise ValueError(f"agent_density: expected a non-negative multiplier (1.0 = normal traffic), "
                             f"got {agent_density!r}")
        return cls(int(height), int(width), tuple(resolve_camera_names(cameras)), int(clip_len), float(fps),
                   _check_mix("weather_mix", weather_mix, WEATHERS, DEFAULT_WEATHER_MIX),
                   _check_mix("time_of_day_mix", time_of_day_mix, TIMES_OF_DAY, DEFAULT_TIME_OF_DAY_MIX),
                   float(agent_density))


@dataclass
class SyntheticSample:
    """A generated clip with the simulation behind it.

    clip: the Clip; plan: the planned scene (road, traffic, ego plan); states: per-frame
    simulation states; renderer: renders any frame and camera again, e.g. instance masks.
    """

    clip: Clip
    plan: ScenePlan
    states: list[FrameState]
    renderer: ClipRenderer

    def instance_ids(self, frame: int, camera: str | int = 0) -> np.ndarray:
        """(h, w) int64 agent track ids seen by `camera` (name or view index) at `frame`; −1 where
        no agent is visible. Nearer agents and scenery occlude farther agents."""
        names = [c.name for c in self.clip.cameras or []]
        if isinstance(camera, str):
            if camera not in names:
                raise ValueError(f"camera: expected one of {names}, got {camera!r}")
            camera = names.index(camera)
        if not 0 <= camera < len(names):
            raise ValueError(f"camera: expected a view index 0..{len(names) - 1}, got {camera}")
        if not 0 <= frame < len(self.states):
            raise ValueError(f"frame: expected 0..{len(self.states) - 1}, got {frame}")
        return self.renderer.instance_ids(self.states[frame], camera)


def sample_from_rng(rng: np.random.Generator, config: WorldConfig, scenario: Scenario | None = None,
                    clip_id: str = "synthetic", meta: dict[str, Any] | None = None,
                    render_rate: float | None = None) -> SyntheticSample:
    """Generate one sample drawing every random choice from `rng`.

    render_rate: render only the frames that resampling the clip to this rate keeps (`resample_indices`); the
    simulation and every label still run at `config.fps`, so those frames, their actions and labels are exactly what
    `resample_clip(full_clip, render_rate)` returns, at a fraction of the rendering. The sample's `states` stay
    per simulation step; the clip holds the kept frames only. None: every frame."""
    scenario = scenario or Scenario()
    if not isinstance(scenario, Scenario):
        raise ValueError(f"scenario: expected a Scenario or None, got {type(scenario).__name__}")
    if scenario.ego_actions is not None and np.shape(scenario.ego_actions) != (config.clip_len, 2):
        raise ValueError(f"scenario.ego_actions: expected shape ({config.clip_len}, 2), "
                         f"got {np.shape(scenario.ego_actions)}")
    setting = draw_setting(rng, scenario, config.weather_mix, config.time_of_day_mix)
    plan = make_plan(rng, scenario, setting, config.clip_len, config.fps, config.agent_density)
    states = simulate(plan, config.clip_len, config.fps)
    appearance = make_appearance(np.random.default_rng([plan.appearance_seed, 1]), setting.weather,
                                 setting.time_of_day, setting.environment)
    cameras = build_rig(list(config.cameras), config.height, config.width)
    renderer = ClipRenderer(plan, cameras, appearance)
    captioner = Captioner(np.random.default_rng([plan.appearance_seed, 2]), setting)
    timestamps = np.arange(config.clip_len) / config.fps
    kept = np.arange(config.clip_len) if render_rate is None else resample_indices(timestamps, render_rate)
    frames = np.empty((len(cameras), len(kept), 3, config.height, config.width), np.uint8)
    step_metas = [frame_meta(plan.world, state) for state in states]
    # every step captioned, kept or not: the captioner draws from its generator step by step
    texts = [captioner.caption(state, fm) for state, fm in zip(states, step_metas)]
    agents, metas = [], []
    for k, i in enumerate(kept):
        frames[:, k] = renderer.render(states[i], int(i)).transpose(0, 3, 1, 2)
        fm = step_metas[i]
        fm["boxes_2d"] = renderer.boxes_2d(states[i], LABEL_RANGE)
        agents.append(agent_boxes(plan.world, states[i]))
        metas.append(fm)
    actions = np.array([[states[i].speed, states[i].curvature] for i in kept], dtype=np.float32)
    clip = Clip(clip_id, frames, timestamps[kept], actions, [texts[i] for i in kept], agents, cameras,
                clip_meta(plan, metas[0], meta or {}), metas)
    return SyntheticSample(clip, plan, states, renderer)


def clip_meta(plan: ScenePlan, first: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
    """Clip-level metadata; traffic_light / intersection / crossing describe the first frame."""
    setting = plan.setting
    geo = plan.layout.geometry
    return {"source": "synthetic", **extra, "weather": setting.weather, "time_of_day": setting.time_of_day,
            "country": setting.country, "environment": setting.environment,
            "drive_side": "right" if geo.drive_sign < 0 else "left", "speed_limit": setting.speed_limit,
            "speed_sign": setting.speed_sign, "lanes": geo.lanes, "lane_types": list(setting.lane_types),
            "lane_width": round(geo.lane_width, 3), "behaviour": plan.ego_plan.behaviour,
            "traffic_light": first["traffic_light"], "intersection": first["intersection"],
            "crossing": first["crossing"]}


def generate_sample(seed: int = 0, *, height: int = 64, width: int = 112, cameras: int | Sequence[str] = ("front",),
                    clip_len: int = 8, fps: float = 25.0, weather_mix: Mapping[str, float] | None = None,
                    time_of_day_mix: Mapping[str, float] | None = None, agent_density: float = 1.0,
                    scenario: Scenario | None = None, clip_id: str | None = None) -> SyntheticSample:
    """Like generate_clip, keeping the simulation (for instance masks and re-rendering)."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed: expected a non-negative integer, got {seed!r}")
    config = WorldConfig.make(height, width, cameras, clip_len, fps, weather_mix, time_of_day_mix, agent_density)
    return sample_from_rng(np.random.default_rng(int(seed)), config, scenario, clip_id or f"synthetic-s{seed}",
                           {"seed": int(seed)})


def generate_clip(seed: int = 0, *, height: int = 64, width: int = 112, cameras: int | Sequence[str] = ("front",),
                  clip_len: int = 8, fps: float = 25.0, weather_mix: Mapping[str, float] | None = None,
                  time_of_day_mix: Mapping[str, float] | None = None, agent_density: float = 1.0,
                  scenario: Scenario | None = None, clip_id: str | None = None) -> Clip:
    """One synthetic multi-camera clip, deterministic in its arguments.

    Args:
        seed: non-negative integer; the same arguments give the same clip.
        height, width: image size in pixels (any size ≥ 16, e.g. 64×112, 288×512, 448×960).
        cameras: names from DEFAULT_CAMERA_NAMES, or a count 1–5 (the first k of them).
        clip_len: frames; fps: frame rate (Hz), also the simulation step.
        weather_mix: probabilities over clear / rain / fog / snow; time_of_day_mix: over day /
            dusk / night (None = defaults; unnormalised weights are fine).
        agent_density: traffic and pedestrian multiplier (0 = empty roads).
        scenario: explicit choices (road, weather, agents, ego actions, ...) for controlled scenes.
        clip_id: defaults to 'synthetic-s<seed>'.

    Returns a Clip with frames (v, t, 3, h, w) uint8, actions (t, 2) (speed m/s, curvature 1/m),
    one caption per frame, agents per frame (3D boxes in the ego frame), camera specs, clip
    metadata and per-frame metadata (incl. 'boxes_2d': camera → 2D boxes).
    """
    return generate_sample(seed, height=height, width=width, cameras=cameras, clip_len=clip_len, fps=fps,
                           weather_mix=weather_mix, time_of_day_mix=time_of_day_mix, agent_density=agent_density,
                           scenario=scenario, clip_id=clip_id).clip
