"""N closed-loop episodes in one batched forward (issue 53, item 4): `VectorDrivingSimulator`, registered as the
vector entry point of "gaia_app/Drive-v0"."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.vector import AutoresetMode

from gaia_app import DRIVE_ENV
from gaia_app.diffusion.ar_sampling import AutoregressiveSampler, TokenPicker
from gaia_app.pipelines.gaia1 import Gaia1Pipeline
from gaia_app.pipelines.simulator import DrivingSimulator, EpisodeOver
from gaia_app.pipelines.simulator_episodes import RowwisePicker
from gaia_app.pipelines.vector_simulator import VectorDrivingSimulator
from gaia_app.weights.folders import shipped_folder

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def pipeline() -> Gaia1Pipeline:
    return Gaia1Pipeline.from_weights(shipped_folder("gaia1"), video_decoder=False)


def commands(steps: int, envs: int, seed: int = 0) -> list[np.ndarray]:
    """`steps` random action batches (envs, 2) float32 inside the command ranges."""
    rng = np.random.default_rng(seed)
    return [np.stack([rng.uniform(6, 14, envs), rng.uniform(-0.03, 0.03, envs)], -1).astype(np.float32)
            for _ in range(steps)]


def test_the_row_picker_draws_each_row_as_a_batch_of_one() -> None:
    """Row i's token is what a batch-1 picker with generator i draws, whatever the other rows hold."""
    picker = RowwisePicker(TokenPicker("top_k", k=5))
    logits = torch.randn(3, 40, generator=torch.Generator().manual_seed(0))
    alone = [picker.picker(logits[i : i + 1], torch.Generator().manual_seed(10 + i)) for i in range(3)]
    batched = picker(logits, [torch.Generator().manual_seed(10 + i) for i in range(3)])
    assert torch.equal(batched, torch.cat(alone))
    logits[0] = torch.randn(40)  # another first row changes nothing for the others
    again = picker(logits, [torch.Generator().manual_seed(10 + i) for i in range(3)])
    assert torch.equal(again[1:], batched[1:])
    with pytest.raises(ValueError, match="one generator per row"):
        picker(logits, [torch.Generator()])


def test_make_vec_gives_the_batched_env() -> None:
    envs = gymnasium.make_vec(DRIVE_ENV, num_envs=2, max_steps=3)
    assert isinstance(envs, VectorDrivingSimulator) and envs.metadata["autoreset_mode"] is AutoresetMode.NEXT_STEP
    assert envs.observation_space.shape == (2, 64, 112, 3) and envs.action_space.shape == (2, 2)
    assert envs.single_observation_space.shape == (64, 112, 3)
    obs, infos = envs.reset(seed=0)
    assert obs.shape == (2, 64, 112, 3) and obs.dtype == np.uint8 and envs.observation_space.contains(obs)
    obs, rewards, terminations, truncations, infos = envs.step(envs.action_space.sample())
    assert obs.shape == (2, 64, 112, 3) and rewards.shape == terminations.shape == truncations.shape == (2,)
    assert infos["tokens"].shape == (2, 8, 14) and infos["_tokens"].all() and infos["step"].tolist() == [1, 1]


def greedy(pipeline: Gaia1Pipeline) -> Gaia1Pipeline:
    """The pipeline with argmax token picking: no draw can land on the other side of a boundary that float
    rounding moved (a batched forward's logits differ from a batch of one by ~4e-6)."""
    sampler = AutoregressiveSampler(TokenPicker("argmax"))
    return Gaia1Pipeline(pipeline.tokenizer, pipeline.world_model, pipeline.image_size, sampler=sampler,
                         rate=pipeline.rate)


def test_sub_episodes_are_the_single_env_episodes_of_their_clips(pipeline: Gaia1Pipeline) -> None:
    """N = 2 from two clips, 3 steps of different commands, greedy picking: each sub-episode equals the single env
    reset with its clip and fed its commands, token for token (the batched session conditions and windows each
    row as a batch-1 session does); observations within one grey level (the tokenizer decodes the batch
    together)."""
    pipeline = greedy(pipeline)
    envs = VectorDrivingSimulator(pipeline, 2, max_steps=5)
    first, _ = envs.reset(seed=[3, 4], options={"index": [0, 1]})
    actions = commands(3, 2)
    vector = [envs.step(a) for a in actions]
    for i, (seed, index) in enumerate(((3, 0), (4, 1))):
        env = DrivingSimulator(pipeline, max_steps=5)
        obs, _ = env.reset(seed=seed, options={"index": index})
        assert np.abs(obs.astype(int) - first[i]).max() <= 1
        for a, (v_obs, *_, v_info) in zip(actions, vector):
            obs, *_, info = env.step(a[i])
            assert np.array_equal(info["tokens"], v_info["tokens"][i])
            assert np.abs(obs.astype(int) - v_obs[i]).max() <= 1
    assert not np.array_equal(vector[-1][4]["tokens"][0], vector[-1][4]["tokens"][1])


def test_each_sub_episode_samples_with_its_own_seed(pipeline: Gaia1Pipeline) -> None:
    """Top-k sampling (the shipped setting): two sub-episodes with one clip, one seed and the same commands are the
    same episode; with another seed the other row changes and the first does not."""
    actions = [np.repeat(a[:1], 2, axis=0) for a in commands(2, 1)]

    def episode(seeds: list[int]) -> np.ndarray:
        envs = VectorDrivingSimulator(pipeline, 2)
        envs.reset(seed=seeds)
        return np.stack([envs.step(a)[4]["tokens"] for a in actions], axis=1)  # (2, steps, h, w)

    same, other = episode([5, 5]), episode([5, 6])
    assert np.array_equal(same[0], same[1]) and np.array_equal(other[0], same[0])
    assert not np.array_equal(other[1], same[1])


def test_a_step_is_one_batched_forward_per_token(pipeline: Gaia1Pipeline) -> None:
    """Every world-model forward of a vector step carries all N episodes, and a step makes as many forwards as a
    single env's step (one per image token), not N times as many."""
    net, calls = pipeline.world_model, []
    decode = net.decode
    net.decode = lambda x, cache=None: calls.append(x.shape[0]) or decode(x, cache)
    try:
        envs = VectorDrivingSimulator(pipeline, 3)
        envs.reset(seed=0)
        envs.step(commands(1, 3)[0])  # opens the session (its prefill)
        calls.clear()
        envs.step(commands(1, 3, 1)[0])
        vector_calls = list(calls)
        env = DrivingSimulator(pipeline)
        env.reset(seed=0)
        env.step([10.0, 0.0])
        calls.clear()
        env.step([11.0, 0.0])
    finally:
        del net.decode
    assert set(vector_calls) == {3} and len(vector_calls) == len(calls) == pipeline.world_model.n


def test_episodes_truncate_together_and_autoreset_on_the_next_step(pipeline: Gaia1Pipeline) -> None:
    envs = VectorDrivingSimulator(pipeline, 2, max_steps=2)
    with pytest.raises(EpisodeOver, match="before reset"):
        envs.step(commands(1, 2)[0])
    first, _ = envs.reset(seed=7)
    again, _ = envs.reset(seed=7)
    assert np.array_equal(first, again)
    truncations = [envs.step(a)[3] for a in commands(2, 2)]
    assert truncations[0].tolist() == [False, False] and truncations[1].tolist() == [True, True]
    obs, rewards, terminations, truncated, infos = envs.step(commands(1, 2)[0])  # the autoreset step
    assert infos["step"].tolist() == [0, 0] and not truncated.any() and not terminations.any()
    assert np.array_equal(obs, first) and rewards.tolist() == [0.0, 0.0]  # same clip: the same context frames
    assert envs.step(commands(1, 2)[0])[4]["step"].tolist() == [1, 1]


@pytest.mark.parametrize(("call", "error", "fragment"), [
    (lambda e: e.step(np.zeros(2, np.float32)), ValueError, r"actions of shape \(2,\): expected \(2, 2\)"),
    (lambda e: e.step([["10", "0"], ["10", "0"]]), TypeError, "not text, booleans or None"),
    (lambda e: e.step([[90.0, 0.0], [10.0, 0.0]]), ValueError, r"speed must lie in \[0, 70\] m/s"),
    (lambda e: e.reset(seed=[1]), ValueError, r"seed=\[1\]: expected one integer or 2"),
    (lambda e: e.reset(seed=[1, "a"]), TypeError, r"seed\[1\]='a': expected an integer"),
    (lambda e: e.reset(seed=2**63 - 1), ValueError, r"episode i gets seed \+ i, so expected an integer in"),
    (lambda e: e.reset(options={"index": [0, 1, 2]}), ValueError, "reset option index=.*expected one integer or 2"),
    (lambda e: e.reset(options={"index": [0, 1.5]}), TypeError, "reset option index=1.5"),
])
def test_bad_vector_input_is_refused(pipeline: Gaia1Pipeline, call, error, fragment) -> None:
    envs = VectorDrivingSimulator(pipeline, 2)
    envs.reset(seed=0)
    with pytest.raises(error, match=fragment):
        call(envs)


def test_bad_vector_settings_are_refused(pipeline: Gaia1Pipeline) -> None:
    with pytest.raises(ValueError, match=r"num_envs=0: expected an integer in \[1, 1025\)"):
        VectorDrivingSimulator(pipeline, 0)
    with pytest.raises(ValueError, match="observation='video_decoder': the vector env observes through the tokenizer"):
        VectorDrivingSimulator(pipeline, 2, observation="video_decoder")
