"""The simulator as a real Gymnasium environment (issue 53, item 4): registered, env_checker-clean, and every bad
action, seed or option refused with a one-line error naming it, its value and what was expected."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import warnings
from collections.abc import Iterator
from pathlib import Path

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from gaia_app import DRIVE_ENV
from gaia_app.pipelines.gaia1 import Gaia1Pipeline
from gaia_app.pipelines.simulator import DrivingSimulator, EpisodeOver
from gaia_app.weights.folders import shipped_folder

pytestmark = pytest.mark.usefixtures("one_thread")
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def pipeline() -> Gaia1Pipeline:
    return Gaia1Pipeline.from_weights(shipped_folder("gaia1"), video_decoder=False)


@contextlib.contextmanager
def checker_warnings_fail() -> Iterator[None]:
    """Every warning raises, but the checkers' advice that a physical action range is not [-1, 1] (the units are
    the point) and that a wrapped env is not the raw one."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warnings.filterwarnings("ignore", message=".*symmetric and normalized space.*")
        warnings.filterwarnings("ignore", message=".*different from the unwrapped version.*")
        yield


def checked(env: gymnasium.Env) -> None:
    """check_env, its warnings failing the test (checker_warnings_fail)."""
    with checker_warnings_fail():
        check_env(env)


def test_check_env_passes_on_the_env_and_through_make() -> None:
    """check_env on the raw env (gymnasium's advice), and one reset and step through make's wrappers, whose passive
    checker checks the first of each: the checker's own warnings fail the test either way."""
    env = gymnasium.make(DRIVE_ENV, weights="gaia1", max_steps=4)
    assert isinstance(env.unwrapped, DrivingSimulator) and env.spec.id == DRIVE_ENV
    assert isinstance(env.observation_space, gymnasium.spaces.Box) and env.observation_space.dtype == np.uint8
    assert env.observation_space.shape == (64, 112, 3)
    assert env.action_space.dtype == np.float32 and env.action_space.low.tolist() == [0.0, -0.5]
    checked(env.unwrapped)
    with checker_warnings_fail():
        obs, _ = env.reset(seed=3)
        assert env.observation_space.contains(obs)
        obs, reward, terminated, truncated, _ = env.step(np.array([10.0, 0.0], dtype=np.float32))
        assert env.observation_space.contains(obs) and not terminated and not truncated


def test_make_takes_a_weights_folder_path_and_render_mode() -> None:
    env = gymnasium.make(DRIVE_ENV, weights=str(shipped_folder("gaia1")), render_mode="rgb_array")
    obs, _ = env.reset(seed=0)
    assert np.array_equal(env.render(), obs) and env.render() is not env.render()
    with pytest.raises(FileNotFoundError, match="weights=no_such_weights"):
        gymnasium.make(DRIVE_ENV, weights="no_such_weights")
    with pytest.raises(ValueError, match="render_mode='human'"):
        DrivingSimulator(env.unwrapped.pipeline, render_mode="human")


@pytest.mark.parametrize("code", [
    "import gaia_app, gymnasium; env = gymnasium.make('gaia_app/Drive-v0', weights='gaia1')",
    "import gymnasium; env = gymnasium.make('gaia_app:gaia_app/Drive-v0')",  # the module is imported by make
])
def test_make_works_in_a_fresh_interpreter(code: str) -> None:
    script = code + "; obs, _ = env.reset(seed=1); print(obs.shape, env.step([10.0, 0.0])[0].dtype)"
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=120,
                          env={**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stderr[-2000:]
    assert "(64, 112, 3) uint8" in done.stdout


NAN, BIG = float("nan"), 2**70
REFUSED = [  # (call, exception, message fragment)
    (("step", ["10", "0.02"]), TypeError, r"action=\['10', '0.02'\]: expected two numbers"),
    (("step", [True, False]), TypeError, "not text, booleans or None"),
    (("step", [True, 0.02]), TypeError, "not text, booleans"),
    (("step", np.array([True, False])), TypeError, "dtype bool"),
    (("step", None), TypeError, "action=None: expected two numbers"),
    (("step", "fast"), TypeError, "action='fast'"),
    (("step", [NAN, 0.0]), ValueError, "must be finite"),
    (("step", [float("inf"), 0.0]), ValueError, "must be finite"),
    (("step", [90.0, 0.0]), ValueError, r"action=\[90.0, 0.0\]: speed must lie in \[0, 70\] m/s"),
    (("step", [10.0, 0.9]), ValueError, r"curvature in \[-0.5, 0.5\] 1/m"),
    (("step", [1.0, 2.0, 3.0]), ValueError, r"action of shape \(3,\): expected \(2,\)"),
    (("step", [[10.0, 0.0]]), ValueError, r"shape \(1, 2\)"),
    (("reset", {"seed": BIG}), ValueError, rf"seed={BIG}: expected an integer in \[0, {2**63}\)"),
    (("reset", {"seed": -1}), ValueError, r"seed=-1: expected an integer in \[0,"),
    (("reset", {"seed": 1.5}), TypeError, "seed=1.5: expected an integer"),
    (("reset", {"seed": True}), TypeError, "seed=True: expected an integer"),
    (("reset", {"options": "synthetic"}), TypeError, "reset options='synthetic': expected a dict"),
    (("reset", {"options": {"prompt": 123}}), TypeError, "reset option prompt=123: expected a non-empty caption"),
    (("reset", {"options": {"prompt": "  "}}), TypeError, "reset option prompt='  '"),
    (("reset", {"options": {"index": "abc"}}), TypeError, r"reset option index='abc': expected an integer in \[0,"),
    (("reset", {"options": {"index": 1.7}}), TypeError, "reset option index=1.7: expected an integer"),
    (("reset", {"options": {"index": 2.0}}), TypeError, "reset option index=2.0"),
    (("reset", {"options": {"index": -1}}), ValueError, "reset option index=-1: expected an integer in"),
    (("reset", {"options": {"world_seed": BIG}}), ValueError, f"reset option world_seed={BIG}"),
    (("reset", {"options": {"context": "video"}}), ValueError, "reset option context='video': expected one of"),
    (("reset", {"options": {"context": "folder"}}), TypeError, "reset option folder=None: context='folder' needs"),
    (("reset", {"options": {"guidance": True}}), ValueError, "reset option guidance=True"),
    (("reset", {"options": {"weather": "snow"}}), ValueError, r"reset options \['weather'\]: expected keys among"),
]


def test_bad_actions_seeds_and_options_are_refused_with_one_line(pipeline: Gaia1Pipeline) -> None:
    """Each refusal names the argument, the value and what was expected; a refused reset leaves the running
    episode as it was."""
    env = DrivingSimulator(pipeline, max_steps=50)
    env.reset(seed=0)
    env.step([10.0, 0.0])
    for (method, argument), error, fragment in REFUSED:
        call = (lambda: env.step(argument)) if method == "step" else (lambda: env.reset(**argument))
        with pytest.raises(error, match=fragment) as caught:
            call()
        assert "\n" not in str(caught.value), f"{method}({argument!r}): the message spans lines"
    assert env.steps == 1 and len(env.tokens) == 5  # still the episode started above
    assert env.step([10.0, 0.0])[4]["step"] == 2


def test_a_truncated_episode_needs_a_reset(pipeline: Gaia1Pipeline) -> None:
    env = DrivingSimulator(pipeline, max_steps=2)
    with pytest.raises(gymnasium.error.ResetNeeded, match="before reset"):
        env.step([10.0, 0.0])
    env.reset(seed=0)
    assert not env.step([10.0, 0.0])[3] and env.step([10.0, 0.0])[3]
    for _ in range(2):  # and stays refused: nothing was sampled
        with pytest.raises(EpisodeOver, match=r"after the episode was truncated at step 2 \(max_steps=2\)"):
            env.step([10.0, 0.0])
    assert len(env.tokens) == 6 and issubclass(EpisodeOver, RuntimeError)
    env.reset(seed=0)
    assert env.step([10.0, 0.0])[4]["step"] == 1


def test_reset_without_a_seed_follows_the_seeded_generator(pipeline: Gaia1Pipeline) -> None:
    """Gymnasium's rule: reset() after reset(seed=s) continues the generator s seeded, so the pair repeats."""
    env = DrivingSimulator(pipeline, max_steps=3)

    def unseeded_tokens() -> np.ndarray:
        env.reset()
        return env.step([10.0, 0.0])[4]["tokens"]

    env.reset(seed=11)
    first = unseeded_tokens()
    env.reset(seed=11)
    assert np.array_equal(unseeded_tokens(), first)
    env.reset(seed=12)
    assert not np.array_equal(unseeded_tokens(), first)
