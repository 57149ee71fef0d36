"""benchmarks/bench_simulator_step.py: the paths it times side by side are the simulator with the samplers they name."""

from __future__ import annotations

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


def test_the_profile_names_the_operators_of_a_step() -> None:
    bench = load_benchmark("bench_simulator_step")
    env = bench.paths(Gaia1Pipeline.from_weights(shipped_folder("gaia1"), video_decoder=False), full=False)["session"]
    table = bench.profile_table(env, steps=1)
    assert "Self CPU" in table and "aten::" in table
