"""Controllability probes and metrics (gaia_app/eval/controllability.py, gaia_app/models/probes.py)."""

from __future__ import annotations

import pytest
import torch

from gaia_app.data.synthetic import SyntheticClipDataset
from gaia_app.eval.controllability import action_error, attribute_accuracy, probe_clips, train_probes
from gaia_app.models.probes import ATTRIBUTES, InverseDynamicsProbe, SceneAttributeProbe


@pytest.fixture(scope="module")
def clips():
    world = SyntheticClipDataset(num_clips=4, seed=5, height=32, width=48, clip_len=13)
    return probe_clips([world[i] for i in range(4)], rate=6.25, frames=4)


def test_probe_clips_carry_frames_actions_and_labels(clips) -> None:
    assert clips.frames.shape == (4, 4, 3, 32, 48) and clips.actions.shape == (4, 4, 2)
    assert set(clips.labels) == set(ATTRIBUTES) and all(v.shape == (4, 4) for v in clips.labels.values())
    assert clips.frames.min() >= -1 and clips.frames.max() <= 1


def test_probes_learn_a_tiny_batch(clips) -> None:
    _, _, fit = train_probes(clips, steps=120, batch=8, lr=3e-3, progress=False)
    assert fit["last_loss"] < fit["first_loss"] / 3, fit


class ConstantDynamics(InverseDynamicsProbe):
    def forward(self, pair: torch.Tensor) -> torch.Tensor:
        return torch.tensor([[10.0, 0.01]]).expand(pair.shape[0], 2)


def test_action_error_scores_only_the_steps_into_generated_frames() -> None:
    frames = torch.zeros(2, 5, 3, 8, 8)
    commanded = torch.tensor([10.0, 0.01]).repeat(2, 5, 1)
    commanded[:, :2] = 99.0  # a_0, a_1 lead into frames 1, 2: not scored from start = 3
    commanded[:, 4] = 99.0  # a_4 leads past the last frame: never scored
    commanded[:, 3, 0] = 12.0  # a_3 → frame 4: speed off by 2 on one of the two scored steps
    assert action_error(ConstantDynamics(), frames, commanded, start=3) == pytest.approx(
        {"speed_mae": 1.0, "curvature_mae": 0.0})


class FixedScene(SceneAttributeProbe):
    def forward(self, frames: torch.Tensor) -> dict[str, torch.Tensor]:
        logits = torch.zeros(frames.shape[0], len(ATTRIBUTES["time_of_day"]))
        logits[::2, 2] = 1.0  # every other frame looks like night, the others like day
        return {"time_of_day": logits}


def test_attribute_accuracy_is_the_share_of_frames_on_target() -> None:
    frames = torch.zeros(2, 3, 3, 8, 8)  # 6 frames: night, day, night, day, night, day
    night = ATTRIBUTES["time_of_day"].index("night")
    assert attribute_accuracy(FixedScene(), frames, {"time_of_day": torch.full((2,), night)}) == {"time_of_day": 0.5}
