"""The GAIA-2 action table's ceiling (tasks/gaia2_actions.py): the rig world re-simulated with commanded actions."""

from __future__ import annotations

import numpy as np
from hydra import compose, initialize_config_dir

from gaia_app.tasks.gaia2_actions import resimulated, rig_world
from tests.test_configs import CONF_DIR


def rig_config():
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose("generate", overrides=["model=gaia2", "data=synthetic_rig", "context.seed=5"])


def test_resimulating_the_scene_with_its_own_actions_reproduces_it_and_a_command_changes_it() -> None:
    cfg = rig_config()
    scene = rig_world(cfg, 5, 1, 12)[0]  # not a 'follow' scene: an open-loop ego drops its lead car (planning.py)
    again = resimulated(cfg, 0, scene.actions.astype(np.float64))
    assert again.frames.shape == scene.frames.shape and scene.frames.shape[:2] == (3, 12)
    np.testing.assert_allclose(again.actions, scene.actions, atol=1e-5)
    assert np.abs(again.frames.astype(int) - scene.frames.astype(int)).mean() == 0  # the same scene, the same motion
    braking = scene.actions.astype(np.float64).copy()
    braking[6:, 0] = np.maximum(braking[5, 0] - 4.0 * np.arange(1, 7) / scene.fps, 0)
    braked = resimulated(cfg, 0, braking)
    np.testing.assert_array_equal(braked.frames[:, :6], again.frames[:, :6])  # the context is untouched
    assert np.abs(braked.frames[:, 8:].astype(int) - scene.frames[:, 8:].astype(int)).mean() > 1.0
