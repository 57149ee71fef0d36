"""`SyntheticClipDataset`: clips of the synthetic world generated on the fly.

Clip i is generated from `np.random.default_rng([seed, i])`: it depends only on (seed, i) and the
knobs, never on global random state, the worker process or the order of access, so DataLoader
workers and the main process return identical clips.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np
import torch

from gaia_app.data.clip import Clip
from gaia_app.data.synthetic.commands import ACCELERATION_RANGE, check_acceleration_range, open_loop_command
from gaia_app.data.synthetic.generate import SyntheticSample, WorldConfig, clip_meta, sample_from_rng
from gaia_app.data.synthetic.labels import frame_meta
from gaia_app.data.synthetic.planning import ScenePlan, make_plan
from gaia_app.data.synthetic.scenario import Scenario, draw_setting
from gaia_app.data.synthetic.simulate import FrameState, simulate
from gaia_app.data.transforms import resample_indices

# stream of the per-clip generator that decides whether (and how) clip i is driven open-loop
OPEN_LOOP_STREAM = 7


class SyntheticClipDataset(torch.utils.data.Dataset):
    """`num_clips` synthetic clips; `ds[i]` is a `Clip` (see generate_clip for the knobs).

    driven_share: share of clips whose ego leaves its policy in the middle half of the clip for a random constant
        acceleration and curvature (gaia_app/data/synthetic/commands.py): actions the frames do not give away,
        which a world model needs to learn what a command does. Such clips have meta["open_loop"] = True and
        meta["command_start_s"]: the time (s from the clip's start) of the first frame the command drives.
    open_loop_acceleration: (low, high) m/s² of the open-loop commands' constant acceleration (uniform).
    render_rate: render only the frames that resampling to this rate (Hz) keeps; the simulation and the labels still
        run at `fps`, so a clip equals the full clip resampled to `render_rate` (for consumers that resample anyway:
        25 Hz → 6.25 Hz renders a quarter of the frames). None: every frame.
    """

    def __init__(self, num_clips: int = 64, seed: int = 0, height: int = 64, width: int = 112,
                 cameras: int | Sequence[str] = ("front",), clip_len: int = 8, fps: float = 25.0,
                 weather_mix: Mapping[str, float] | None = None, time_of_day_mix: Mapping[str, float] | None = None,
                 agent_density: float = 1.0, scenario: Scenario | None = None, driven_share: float = 0.0,
                 open_loop_acceleration: Sequence[float] = ACCELERATION_RANGE, render_rate: float | None = None,
                 cache_clips: int = 0):
        if isinstance(num_clips, bool) or not isinstance(num_clips, (int, np.integer)) or num_clips < 1:
            raise ValueError(f"num_clips: expected a positive integer, got {num_clips!r}")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed: expected a non-negative integer, got {seed!r}")
        if scenario is not None and not isinstance(scenario, Scenario):
            raise ValueError(f"scenario: expected a Scenario or None, got {type(scenario).__name__}")
        if not 0.0 <= driven_share <= 1.0:
            raise ValueError(f"driven_share: expected a share in [0, 1], got {driven_share!r}")
        if driven_share > 0 and scenario is not None and scenario.ego_actions is not None:
            raise ValueError("driven_share > 0 with scenario.ego_actions: the clip's actions are given twice")
        if isinstance(cache_clips, bool) or not isinstance(cache_clips, (int, np.integer)) or cache_clips < 0:
            raise ValueError(f"cache_clips: expected a number of clips ≥ 0, got {cache_clips!r}")
        self.num_clips, self.seed, self.scenario = int(num_clips), int(seed), scenario
        self.cache_clips, self.cached = int(cache_clips), OrderedDict()
        self.driven_share = float(driven_share)
        if render_rate is not None and not (np.isfinite(render_rate) and 0 < render_rate <= fps):
            raise ValueError(f"render_rate: expected a rate in (0, fps = {fps:g}] Hz or None, got {render_rate!r}")
        self.render_rate = None if render_rate is None else float(render_rate)
        self.open_loop_acceleration = check_acceleration_range(open_loop_acceleration)
        cameras = cameras if isinstance(cameras, (int, np.integer)) else list(cameras)  # Hydra passes ListConfig
        self.config = WorldConfig.make(height, width, cameras, clip_len, fps, weather_mix, time_of_day_mix,
                                       agent_density)

    def __len__(self) -> int:
        return self.num_clips

    def _rng(self, index: int) -> np.random.Generator:
        if not -self.num_clips <= index < self.num_clips:
            raise IndexError(f"index {index} out of range for {self.num_clips} clips")
        return np.random.default_rng([self.seed, index % self.num_clips])

    def sample(self, index: int) -> SyntheticSample:
        """Clip `index` with its simulation (for instance masks)."""
        rng = self._rng(int(index))
        i = int(index) % self.num_clips
        if i in self.cached:
            self.cached.move_to_end(i)
            return self.cached[i]
        command = self.open_loop_command(i)
        scenario = self.scenario if command is None else replace(self.scenario or Scenario(), ego_actions=command[0])
        meta = {"seed": self.seed, "index": i,
                **({"open_loop": True, "command_start_s": command[1] / self.config.fps} if command else {})}
        sample = sample_from_rng(rng, self.config, scenario, f"synthetic-s{self.seed}-{i:06d}", meta,
                                 self.render_rate)
        if self.cache_clips:
            self.cached[i] = sample
            if len(self.cached) > self.cache_clips:
                self.cached.popitem(last=False)
        return sample

    def open_loop_command(self, index: int) -> tuple[np.ndarray, int] | None:
        """For the `driven_share` of clips that leave their policy: their (t, 2) ego actions and the frame at which
        the command starts (commands.open_loop_command); None for the others."""
        if self.driven_share <= 0:
            return None
        choice = np.random.default_rng([self.seed, index, OPEN_LOOP_STREAM])
        if choice.random() >= self.driven_share:
            return None
        return open_loop_command(choice, self.simulated_actions(index), self.config.fps, self.open_loop_acceleration)

    def __getitem__(self, index: int) -> Clip:
        return self.sample(index).clip

    def steps_at(self, index: int, fps: float | None) -> int:
        """Frames of clip `index` after resampling to `fps` (None: the world's own rate); every clip is as long."""
        self._rng(int(index))  # range check
        timestamps = np.arange(self.config.clip_len) / self.config.fps
        return len(timestamps) if fps is None else len(resample_indices(timestamps, fps))

    def simulate(self, index: int) -> tuple[ScenePlan, list[FrameState]]:
        """The plan and per-frame simulation states of clip `index`, without rendering anything."""
        rng = self._rng(int(index))
        config, scenario = self.config, self.scenario or Scenario()
        setting = draw_setting(rng, scenario, config.weather_mix, config.time_of_day_mix)
        plan = make_plan(rng, scenario, setting, config.clip_len, config.fps, config.agent_density)
        return plan, simulate(plan, config.clip_len, config.fps)

    def simulated_actions(self, index: int) -> np.ndarray:
        """(clip_len, 2) float32 ego (speed m/s, curvature 1/m) of clip `index`, as `ds[index].actions`, unrendered."""
        return np.array([[s.speed, s.curvature] for s in self.simulate(index)[1]], dtype=np.float32)

    def describe(self, index: int) -> dict[str, Any]:
        """Clip-level metadata plus mean 'speed' and 'curvature' of clip `index`, from the
        simulation only (no rendering): cheap features for balanced sampling."""
        plan, states = self.simulate(index)
        meta = clip_meta(plan, frame_meta(plan.world, states[0]), {"seed": self.seed, "index": int(index)})
        meta["speed"] = float(np.mean([s.speed for s in states]))
        meta["curvature"] = float(np.mean([s.curvature for s in states]))
        return meta
