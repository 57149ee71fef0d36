"""The GAIA-2 action table's twin probe: the speed contrast read from two futures side by side
(protocols/gaia2_twin_probe.py, models/probes.py TwinDisplacementProbe)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from gaia_app.eval.controllability import ProbeClips
from gaia_app.models.probes import TwinDisplacementProbe
from gaia_app.protocols import gaia2_twin_probe
from gaia_app.protocols.controllability import commanded_actions
from gaia_app.protocols.gaia2_twin_probe import (
    WEIGHTS,
    displacement,
    load_twin_probe,
    speed_probe,
    train_twin_probe,
    twin_actions,
    twin_data,
    twin_probe,
    twin_speed_row,
)

CONF = Path(__file__).resolve().parents[1] / "conf"
FRAMES, RATE = 8, 12.5
TINY = ["model=gaia2", "data=synthetic_rig", "context.seed=5", "model.evaluate.probe_clips=3",
        "model.evaluate.probe_steps=2", "model.evaluate.speed_probe=twin"]


def rig_config(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("generate", overrides=[*TINY, *overrides])


class TravelledProbe(torch.nn.Module):
    """An oracle: frames filled with the ego's travelled distance (m), read as second − first."""

    def forward(self, pair: torch.Tensor) -> torch.Tensor:
        return pair[:, 1].flatten(1).mean(1) - pair[:, 0].flatten(1).mean(1)


def travelled_video(commanded: torch.Tensor, draws: int) -> torch.Tensor:
    """(C·N·draws, f, 1, 1, 2, 2) frames whose every pixel is the distance travelled up to that frame."""
    travelled = displacement(torch.zeros_like(commanded), commanded, RATE)  # (C·N, f)
    return travelled.repeat_interleave(draws, 0)[:, :, None, None, None, None].expand(-1, -1, 1, 1, 2, 2)


def commands_of(n: int, first: int) -> torch.Tensor:
    rng = np.random.default_rng(0)
    past = torch.from_numpy(np.stack([[[8.0 + rng.uniform(-3, 3), 0.0]] * FRAMES for _ in range(n)])).float()
    contexts = ProbeClips(torch.zeros(n, FRAMES, 3, 4, 4), past, {})
    commands = [("brake", "straight"), ("accelerate", "straight"), ("keep", "left"), ("keep", "right")]
    return commanded_actions(contexts, first, FRAMES - first, RATE, commands)  # (4·n, f, 2)


def test_the_twins_telescope_into_the_horizon_mean_speed_contrast() -> None:
    """Read by an oracle of the true displacement, the twin row recovers the commanded accelerate − brake contrast
    exactly (the telescoping identity of the module docstring); futures that ignore the command read 0, so they score
    the commanded contrast, as the floor does."""
    first, stride, n, draws = 4, 2, 3, 2
    commanded = commands_of(n, first)
    video = travelled_video(commanded, draws)
    row = twin_speed_row(TravelledProbe(), video, commanded, first, stride, 4, (1, 0), RATE, draws)
    wanted = row["realised"]["commanded"]
    assert wanted > 0.5  # accelerate (+2 m/s²) against brake (−4 m/s²) over the horizon
    assert row["realised"]["per_context"] == pytest.approx([wanted] * n, rel=1e-4)
    assert row["speed_contrast"]["mean"] == pytest.approx(0.0, abs=1e-4)
    same = video.unflatten(0, (4, -1))[0].repeat(4, 1, 1, 1, 1, 1)  # every command's future is the brake one
    floor = twin_speed_row(TravelledProbe(), same, commanded, first, stride, 4, (1, 0), RATE, draws)
    assert floor["speed_contrast"]["mean"] == pytest.approx(wanted, rel=1e-4)
    with pytest.raises(ValueError, match="draws"):
        twin_speed_row(TravelledProbe(), video, commanded, first, stride, 4, (1, 0), RATE, draws=3)


def test_displacement_sums_the_speed_gap_up_to_each_frame() -> None:
    slow, fast = np.array([[5.0, 0.0]] * 4), np.array([[5.0, 0.0], [7.0, 0.0], [9.0, 0.0], [9.0, 0.0]])
    assert displacement(slow, fast, 10.0).tolist() == pytest.approx([0.0, 0.0, 0.2, 0.6])


def test_twin_actions_share_the_past_and_the_path() -> None:
    own = np.stack([np.linspace(6, 8, FRAMES), np.full(FRAMES, 0.01)], axis=1)
    rng = np.random.default_rng(3)
    for _ in range(20):
        first, second, t0 = twin_actions(rng, own, RATE)
        assert 1 <= t0 <= FRAMES - 2 and first.shape == second.shape == (FRAMES, 2)
        assert np.array_equal(first[:t0], own[:t0]) and np.array_equal(second[:t0], own[:t0])
        assert np.array_equal(first[t0:, 1], second[t0:, 1])  # one curvature: the same path, other distances
    with pytest.raises(ValueError, match="at least 3 frames"):
        twin_actions(rng, own[:2], RATE)


def test_the_twin_probe_is_antisymmetric_and_reads_identical_futures_as_zero() -> None:
    probe = TwinDisplacementProbe(cameras=3).eval()
    pair = torch.rand(2, 2, 3, 3, 64, 112, generator=torch.Generator().manual_seed(0)) * 2 - 1
    with torch.no_grad():
        torch.testing.assert_close(probe(pair.flip(1)), -probe(pair))
        assert probe(pair[:, :1].expand(-1, 2, -1, -1, -1, -1)).abs().max() == 0
    with pytest.raises(ValueError, match=r"\(b, 2, 3, 3, H, W\)"):
        probe(pair[:, :, :2])


def test_the_twin_probe_learns_to_read_how_far_apart_the_twins_are() -> None:
    """Overfits the twins of three scenes (the front camera, for speed): the smooth-L1 loss (m) falls at least
    fourfold in 120 steps."""
    data = twin_data(rig_config("model.evaluate.probe_cameras=front"), FRAMES)
    assert data.frames.shape == (3, 2, FRAMES, 1, 3, 64, 112) and data.frames.dtype == torch.uint8
    before = data.displacement[torch.arange(3), data.start - 1]
    assert before.abs().max() == 0  # nothing parts the twins before their commands start
    _, fit = train_twin_probe(data, steps=120, batch=8, seed=0, progress=False)
    assert fit["last_loss"] < fit["first_loss"] / 4


def test_a_saved_twin_probe_is_loaded_instead_of_trained_and_checked(tmp_path, monkeypatch) -> None:
    folder = tmp_path / "twin_probe"
    trained, info = twin_probe(rig_config(), FRAMES, save_to=folder)
    assert (folder / WEIGHTS).is_file() and "fit" in info
    monkeypatch.setattr(gaia2_twin_probe, "train_twin_probe", lambda *a, **k: pytest.fail("trained a second probe"))
    loaded, loaded_info = twin_probe(rig_config(f"model.evaluate.twin_probe={folder}"), FRAMES)
    assert loaded_info["loaded_from"] == str(folder)
    pair = torch.rand(2, 2, 3, 3, 64, 112, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        torch.testing.assert_close(loaded(pair), trained(pair))
    with pytest.raises(ValueError, match="probe_cameras='rig'"):
        load_twin_probe(folder, rig_config("model.evaluate.probe_cameras=front"), FRAMES)
    with pytest.raises(ValueError, match="trained on world 4343"):
        load_twin_probe(folder, rig_config("context.seed=4343"), FRAMES)
    with pytest.raises(FileNotFoundError, match=WEIGHTS):
        load_twin_probe(tmp_path, rig_config(), FRAMES)


def test_the_speed_probe_setting_is_checked_and_pair_needs_no_twin_probe() -> None:
    assert twin_probe(rig_config("model.evaluate.speed_probe=pair"), FRAMES) == (None, None)
    with pytest.raises(ValueError, match="model.evaluate.speed_probe='both'"):
        speed_probe(rig_config("model.evaluate.speed_probe=both"))
