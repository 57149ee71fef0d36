"""DataModules: clip-level split, frame and clip batches with every condition, no zero-filled labels."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gaia_app.data.clip import AgentBoxes, CameraSpec, Clip, ClipError
from gaia_app.data.collate import collate_clips
from gaia_app.data.datamodules import ClipDataModule, FrameDataModule, split_by_clip
from gaia_app.data.datasets import clip_to_sample


def make_clip(i: int, t: int = 25, views: int = 2, labelled: bool = True, h: int = 32, w: int = 48) -> Clip:
    rng = np.random.default_rng(i)
    cams = [CameraSpec(f"cam{v}", np.diag([40.0, 40.0, 1.0]) + np.array([[0, 0, w / 2], [0, 0, h / 2], [0, 0, 0]]),
                       np.eye(4), w, h) for v in range(views)]
    agents = [AgentBoxes([[10.0 + k, 0, 0]] * (k % 3), [[4, 2, 1.5]] * (k % 3), [0] * (k % 3), [0] * (k % 3),
                         list(range(k % 3))) for k in range(t)]
    return Clip(
        clip_id=f"clip{i:03d}",
        frames=rng.integers(0, 255, (views, t, 3, h, w), dtype=np.uint8),
        timestamps=np.arange(t) / 25.0,
        actions=np.stack([np.full(t, float(i)), np.zeros(t)], 1) if labelled else None,
        text=[f"frame {k}" for k in range(t)] if labelled else None,
        agents=agents if labelled else None,
        cameras=cams,
        meta={"weather": ["clear", "rain"][i % 2]},
    )


class ListSource:
    def __init__(self, clips):
        self.clips = clips

    def __len__(self):
        return len(self.clips)

    def __getitem__(self, i):
        return self.clips[i]


def test_split_by_clip_is_disjoint_and_deterministic() -> None:
    source = ListSource([make_clip(i, t=2) for i in range(20)])
    train, val = split_by_clip(source, 0.2, seed=0)
    assert len(val) == 4 and len(train) == 16
    assert not set(train.indices) & set(val.indices)
    assert split_by_clip(source, 0.2, seed=0)[1].indices == val.indices


def test_frame_batches_flatten_views_and_frames() -> None:
    dm = FrameDataModule(ListSource([make_clip(i) for i in range(6)]), val_fraction=0.34, batch_size=2,
                         height=32, width=48, frames_per_clip=3)
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    assert batch["image"].shape == (2 * 3 * 2, 3, 32, 48)
    assert batch["image"].min() >= -1 and batch["image"].max() <= 1


def test_clip_batches_resample_by_timestamps_and_carry_conditions() -> None:
    dm = ClipDataModule(ListSource([make_clip(i) for i in range(4)]), val_source=ListSource([make_clip(9)]),
                        batch_size=2, height=32, width=48, clip_len=4, fps=6.25)
    dm.setup("fit")
    batch = next(iter(dm.val_dataloader()))
    assert batch["video"].shape == (1, 2, 4, 3, 32, 48)
    # 25 Hz → 6.25 Hz: consecutive kept frames are 0.16 s apart
    assert torch.allclose(batch["timestamps"][0], torch.tensor([0.0, 0.16, 0.32, 0.48]))
    assert batch["actions"].shape == (1, 4, 2) and batch["actions"][0, 0, 0] == 9.0
    assert batch["intrinsics"].shape == (1, 2, 3, 3) and batch["extrinsics"].shape == (1, 2, 4, 4)
    assert batch["agents_mask"].shape[:2] == (1, 4) and batch["text"][0][1] == "frame 4"


def test_resize_to_model_resolution_updates_intrinsics() -> None:
    dm = ClipDataModule(ListSource([make_clip(0, h=64, w=96)]), val_source=ListSource([make_clip(1, h=64, w=96)]),
                        batch_size=1, height=32, width=48, clip_len=2)
    dm.setup("fit")
    batch = next(iter(dm.val_dataloader()))
    assert batch["video"].shape[-2:] == (32, 48)
    assert batch["intrinsics"][0, 0, 0, 0] == pytest.approx(20.0)


def test_unlabelled_clips_leave_labels_absent() -> None:
    sample = clip_to_sample(make_clip(0, t=3, labelled=False))
    assert "actions" not in sample and "text" not in sample and "agents" not in sample


def test_mixed_labels_in_a_batch_are_an_error_naming_the_clip() -> None:
    samples = [clip_to_sample(make_clip(0, t=3)), clip_to_sample(make_clip(1, t=3, labelled=False))]
    with pytest.raises(ClipError, match="clip001"):
        collate_clips(samples)


def test_too_short_clip_names_the_clip() -> None:
    dm = ClipDataModule(ListSource([make_clip(0, t=5)]), val_source=ListSource([make_clip(1, t=5)]),
                        batch_size=1, height=32, width=48, clip_len=4, fps=6.25)
    dm.setup("fit")
    with pytest.raises(ClipError, match="clip001"):
        next(iter(dm.val_dataloader()))


def test_balanced_loader_uses_metadata() -> None:
    clips = [make_clip(i, t=2) for i in range(12)]
    for c in clips:
        c.meta["weather"] = "rain" if c.clip_id == "clip000" else "clear"
    dm = FrameDataModule(ListSource(clips), val_fraction=0.1, split_seed=1, batch_size=1, height=32, width=48,
                         balance={"features": {"weather": None}, "exponent": 1.0})
    dm.setup("fit")
    loader = dm.train_dataloader()
    assert len(loader) == len(dm.train_set)
    balanced = loader.sampler.inner  # the balancing sampler, inside the resumable loader's order
    assert balanced.weights.max() == 1.0 and balanced.weights.min() < 0.2
