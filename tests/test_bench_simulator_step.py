"""benchmarks/bench_simulator_step.py: the paths it times side by side are the simulator with the samplers they name."""

from __future__ import annotations

import pytest

from gaia_app.pipelines.gaia1 import Gaia1Pipeline
from gaia_app.weights.folders import shipped_folder
from tests.conftest import load_benchmark


def test_the_compiled_path_is_the_session_with_the_compiled_decode_step() -> None:
    bench = load_benchmark("bench_simulator_step")
    pipeline = Gaia1Pipeline.from_weights(shipped_folder("gaia1"), video_decoder=False)
    envs = bench.paths(pipeline, full=True, compiled=True)
    assert list(envs) == ["session", "window per step", "session, compiled decode", "full recompute"]
    samplers = {name: env.pipeline.rollouts.sampler for name, env in envs.items()}
    assert samplers["session"].decode_step == "eager"
    assert samplers["session, compiled decode"].decode_step == "compiled"
    assert samplers["full recompute"].use_cache is False
    assert all(env.pipeline.world_model is pipeline.world_model for env in envs.values())  # the same nets
    assert list(bench.paths(pipeline, full=False)) == ["session", "window per step"]
    blocked_paths = bench.paths(pipeline, full=False, compiled=True, blocks=(4,))
    blocked = blocked_paths["session, compiled decode, 4 tokens per call"]
    assert blocked.pipeline.rollouts.sampler.decode_step == "compiled"
    assert blocked.pipeline.rollouts.sampler.tokens_per_call == 4


@pytest.mark.slow  # the profiler over a whole simulator step (13 s)
def test_the_profile_names_the_operators_of_a_step() -> None:
    bench = load_benchmark("bench_simulator_step")
    env = bench.paths(Gaia1Pipeline.from_weights(shipped_folder("gaia1"), video_decoder=False), full=False)["session"]
    table = bench.profile_table(env, steps=1)
    assert "Self CPU" in table and "aten::" in table


class CountingEnv:
    """Records what `episode_rate` asks of an env."""

    def __init__(self) -> None:
        self.resets: list[int] = []
        self.steps = 0

    def reset(self, seed: int, options: dict) -> None:
        self.resets.append(seed)

    def step(self, action: list[float]) -> None:
        self.steps += 1


def test_skipped_steps_run_before_the_clock_starts() -> None:
    bench = load_benchmark("bench_simulator_step")
    env = CountingEnv()
    rate = bench.episode_rate(env, steps=3, seed=5, skip=8)
    assert env.resets == [5] and env.steps == 11 and rate > 0


def test_a_skip_of_the_window_makes_every_timed_step_slide() -> None:
    """With 4 context frames and T = 12, the 9th step is the first that drops a step from the window."""
    bench = load_benchmark("bench_simulator_step")
    env = bench.paths(Gaia1Pipeline.from_weights(shipped_folder("gaia1"), video_decoder=False), full=False)["session"]
    frames = env.pipeline.world_model.frames
    bench.episode_rate(env, steps=1, seed=0, skip=frames - 4)
    assert env.episodes.session.dropped_steps == 1


def test_the_window_prefill_is_timed_on_the_open_session() -> None:
    bench = load_benchmark("bench_simulator_step")
    env = bench.paths(Gaia1Pipeline.from_weights(shipped_folder("gaia1"), video_decoder=False), full=False)["session"]
    net = env.pipeline.world_model
    bench.episode_rate(env, steps=1, seed=0)
    with pytest.raises(ValueError, match="after a slide"):  # the window is not full yet
        bench.window_prefill_ms(env, repeats=1)
    bench.episode_rate(env, steps=1, seed=0, skip=net.frames - 4)
    prefill = bench.window_prefill_ms(env, repeats=1)
    assert prefill["positions"] == (net.frames - 1) * net.step_len + net.m  # the last T − 1 steps and the text
    assert prefill["batch"] == env.episodes.session.streams.text.shape[0] and prefill["ms"] > 0
    assert abs(prefill["budget_ms_at_3x"] - 1000 / 18.75) < 1e-9
