"""The GAIA-2 action table's ceiling (protocols/gaia2_actions.py): the rig world re-simulated with commanded actions."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from gaia_app.protocols.gaia2_actions import (
    mirror_order,
    noise_draws,
    probe_mirror,
    probe_stride,
    probe_views,
    resimulated,
    rig_world,
    views_of,
)
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


def test_the_rig_probe_reads_every_camera_in_rig_order_and_mirrors_left_and_right() -> None:
    cfg = rig_config()
    assert probe_views(cfg) == [0, 1, 2]  # the default: every camera, in rig order
    cfg.model.evaluate.probe_cameras = "front"
    assert probe_views(cfg) is None  # the rig's first camera alone
    assert mirror_order(["front", "front_left", "front_right"]) == [0, 2, 1]
    assert mirror_order(["rear_left", "front", "rear_right"]) == [2, 1, 0]
    frames = torch.arange(3 * 4 * 3 * 4 * 4, dtype=torch.float32).view(3, 4, 3, 4, 4)  # (v, t, 3, H, W)
    assert torch.equal(views_of(frames, None), frames[0])
    assert torch.equal(views_of(frames, [0, 1, 2])[2, 1], frames[1, 2])  # (t, k, 3, H, W)


def test_the_rig_probe_refuses_a_rig_without_mirror_twins_and_an_unknown_choice() -> None:
    with pytest.raises(ValueError, match=r"\['front_left'\] have no mirror twin"):
        mirror_order(["front", "front_left"])
    cfg = rig_config()
    cfg.data.source.cameras = ["front", "front_left"]
    with pytest.raises(ValueError, match=r"use model.evaluate.probe_cameras=front"):
        probe_mirror(cfg)
    cfg.model.evaluate.probe_cameras = "front"
    assert probe_mirror(cfg) is None
    cfg.model.evaluate.probe_cameras = "all"
    with pytest.raises(ValueError, match=r"model.evaluate.probe_cameras='all': expected one of \('front', 'rig'\)"):
        probe_views(cfg)


@pytest.mark.parametrize("stride", [0, 5, 1.5, "2"])
def test_a_probe_stride_outside_one_latent_step_is_refused(stride) -> None:
    cfg = rig_config()
    assert probe_stride(cfg) == cfg.model.evaluate.probe_stride
    cfg.model.evaluate.probe_stride = stride
    with pytest.raises(ValueError, match=rf"model.evaluate.probe_stride={stride!r}: expected a whole number"):
        probe_stride(cfg)


@pytest.mark.parametrize("draws", [0, -1, 2.0])
def test_noise_draws_must_be_a_whole_number_of_futures(draws) -> None:
    cfg = rig_config()
    assert noise_draws(cfg) == cfg.model.evaluate.noise_draws == 1
    cfg.model.evaluate.noise_draws = draws
    with pytest.raises(ValueError, match=rf"model.evaluate.noise_draws={draws!r}: expected a whole number ≥ 1"):
        noise_draws(cfg)
