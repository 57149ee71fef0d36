"""The closed-loop driving simulator (issue 25, items 1 and 4) on the shipped GAIA-1 reference weights."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gaia_app.pipelines.gaia1 import Gaia1Pipeline
from gaia_app.pipelines.simulator import DrivingSimulator
from gaia_app.utils.shipped import shipped_folder

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def pipeline() -> Gaia1Pipeline:
    return Gaia1Pipeline.from_weights(shipped_folder("gaia1"), video_decoder=False)


def test_spaces_and_episode_follow_the_gymnasium_api(pipeline: Gaia1Pipeline) -> None:
    env = DrivingSimulator(pipeline, context_frames=4, max_steps=3)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs) and obs.shape == (64, 112, 3) and info["step"] == 0
    assert env.action_space.shape == (2,) and env.action_space.contains(env.action_space.sample(np.random.default_rng(0)))
    for k in range(3):
        obs, reward, terminated, truncated, info = env.step([10.0, 0.02])
        assert env.observation_space.contains(obs) and reward == 0.0 and not terminated
        assert truncated == (k == 2) and info["step"] == k + 1 and info["action"] == pytest.approx([10.0, 0.02])
    assert np.array_equal(env.render(), obs)


def test_steps_are_deterministic_under_a_seed(pipeline: Gaia1Pipeline) -> None:
    def episode(seed: int) -> list[np.ndarray]:
        env = DrivingSimulator(pipeline)
        env.reset(seed=seed, options={"index": 1})
        return [env.step([8.0, -0.02])[4]["tokens"] for _ in range(3)]

    first, again, other = episode(3), episode(3), episode(4)
    assert all(np.array_equal(a, b) for a, b in zip(first, again))
    assert not all(np.array_equal(a, b) for a, b in zip(first, other))


def test_a_closed_loop_episode_reproduces_the_open_loop_rollout_of_its_actions(pipeline: Gaia1Pipeline) -> None:
    """Context of T − 1 frames, so both run the window every step from the same positions: equal tokens."""
    window = int(pipeline.world_model.frames)
    env = DrivingSimulator(pipeline, context_frames=window - 1)
    env.reset(seed=7)
    context = env.tokens.clone()
    commands = [[9.0, 0.0], [11.0, 0.02], [12.0, 0.02], [10.0, -0.03]]
    closed = torch.stack([torch.from_numpy(env.step(a)[4]["tokens"]) for a in commands])
    actions = torch.from_numpy(np.stack(env.actions))[None]
    generator = torch.Generator().manual_seed(7)
    opened, _ = pipeline.sample_batch(context[None], len(commands), None, actions, None, 1, generator)
    assert torch.equal(closed, opened[0, window - 1:].cpu())


def test_bad_actions_are_named(pipeline: Gaia1Pipeline) -> None:
    env = DrivingSimulator(pipeline, max_steps=2)
    with pytest.raises(RuntimeError, match="reset"):
        env.step([5.0, 0.0])
    env.reset(seed=0)
    for action, match in (([float("nan"), 0.0], "finite"), ([1.0, 2.0, 3.0], r"shape \(3,\)"),
                          ([90.0, 0.0], r"speed must lie in \[0, 70\] m/s"), (["fast", 0.0], "two numbers")):
        with pytest.raises(ValueError, match=match):
            env.step(action)
    with pytest.raises(ValueError, match="context='none' .* give prompt"):
        env.reset(options={"context": "none"})
    with pytest.raises(ValueError, match="reset options"):
        env.reset(options={"weather": "snow"})


def test_an_episode_can_start_from_a_prompt_alone(pipeline: Gaia1Pipeline) -> None:
    env = DrivingSimulator(pipeline, max_steps=2)
    obs, info = env.reset(seed=1, options={"context": "none", "prompt": "It is night."})
    assert env.observation_space.contains(obs) and len(env.tokens) == 1
    obs, *_ = env.step([8.0, 0.0])
    assert len(env.tokens) == 2
