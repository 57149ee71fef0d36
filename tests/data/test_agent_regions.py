"""Agent boxes projected into frames (gaia_app/data/agent_regions.py) and the frames datamodule that carries them."""

from __future__ import annotations

from dataclasses import replace

import pytest

from gaia_app.data.agent_regions import agent_box_masks
from gaia_app.data.datamodules import FrameDataModule
from gaia_app.data.datasets import FramesDataset, fit_to_resolution
from gaia_app.data.synthetic import SyntheticClipDataset


@pytest.fixture(scope="module")
def world() -> SyntheticClipDataset:
    return SyntheticClipDataset(num_clips=4, seed=77, height=64, width=112, clip_len=6)


def test_projected_boxes_hold_the_rendered_agents(world) -> None:
    inside = agents = 0
    for i in range(len(world)):
        sample = world.sample(i)
        boxes = agent_box_masks(sample.clip)
        assert boxes.shape == (1, 6, 64, 112)
        for f in range(6):
            ids = sample.instance_ids(f, 0) >= 0
            inside, agents = inside + (ids & boxes[0, f]).sum(), agents + ids.sum()
    assert agents > 0 and inside / agents > 0.95  # what falls outside is rounding at box edges


def test_boxes_follow_a_resize(world) -> None:
    clip = world[0]
    small = agent_box_masks(fit_to_resolution(clip, 32, 56, "crop"))
    full = agent_box_masks(clip)
    assert small.shape == (1, 6, 32, 56)
    assert abs(small.mean() - full.mean()) < 0.02  # the same share of the image, at half the size


def test_a_clip_without_boxes_or_cameras_is_named(world) -> None:
    clip = world[0]
    with pytest.raises(ValueError, match=r"clip 'synthetic-s77-000000' has no agent boxes \(clip.agents\)"):
        agent_box_masks(replace(clip, agents=None))
    with pytest.raises(ValueError, match=r"has no camera specs \(clip.cameras\)"):
        agent_box_masks(replace(clip, cameras=None))


def test_frames_carry_their_boxes(world) -> None:
    item = FramesDataset(world, 64, 112, frames_per_clip=3, agent_boxes=True)[1]
    assert item["image"].shape == (3, 3, 64, 112) and item["agent_box"].shape == (3, 64, 112)
    assert "agent_box" not in FramesDataset(world, 64, 112, frames_per_clip=3)[1]
    data = FrameDataModule(world, batch_size=2, num_workers=0, height=64, width=112, frames_per_clip=2,
                           agent_boxes=True)
    data.setup("fit")
    batch = next(iter(data.train_dataloader()))
    assert batch["agent_box"].shape == (4, 64, 112) and str(batch["agent_box"].dtype) == "torch.bool"
