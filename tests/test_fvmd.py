"""FVMD: tracks follow a known motion; identical clip sets score ≈ 0, jittered clips score far higher."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gaia_app.data.synthetic import SyntheticClipDataset
from gaia_app.eval.fvmd import FEATURE_DIM, FVMD, motion_features, to_gray_uint8, track


@pytest.fixture(scope="module")
def clips() -> torch.Tensor:
    """(12, 16, 3, 64, 112) front-camera synthetic clips at 25 Hz in [-1, 1]."""
    data = SyntheticClipDataset(num_clips=12, seed=7, height=64, width=112, clip_len=16, cameras=1)
    frames = np.stack([data[i].frames[0] for i in range(len(data))])
    return torch.from_numpy(frames).float() / 127.5 - 1


def jitter(clips: torch.Tensor, pixels: int, seed: int) -> torch.Tensor:
    """Shift every frame by its own random whole-pixel offset (camera shake)."""
    g = torch.Generator().manual_seed(seed)
    out = clips.clone()
    for b in range(clips.shape[0]):
        for t in range(clips.shape[1]):
            dy, dx = torch.randint(-pixels, pixels + 1, (2,), generator=g).tolist()
            out[b, t] = torch.roll(clips[b, t], shifts=(dy, dx), dims=(-2, -1))
    return out


def test_tracks_follow_a_known_translation() -> None:
    g = torch.Generator().manual_seed(0)
    texture = torch.nn.functional.avg_pool2d(torch.rand(1, 3, 80, 120, generator=g) * 2 - 1, 3, 1, 1)[0]
    clip = torch.stack([torch.roll(texture, shifts=(0, 2 * i), dims=(-2, -1)) for i in range(6)])[:, :, 8:72, 8:112]
    tracks = track(to_gray_uint8(clip))
    steps = np.diff(tracks.points, axis=0)[tracks.valid[1:]]
    assert len(steps) > 50
    np.testing.assert_allclose(np.median(steps, axis=0), [2.0, 0.0], atol=0.1)


def test_motion_features_have_the_documented_size_and_need_three_frames(clips: torch.Tensor) -> None:
    tracks = track(to_gray_uint8(clips[0]))
    assert motion_features(tracks).shape == (FEATURE_DIM,)
    with pytest.raises(ValueError, match="at least 3 frames"):
        motion_features(track(to_gray_uint8(clips[0, :2])))
    with pytest.raises(ValueError, match=r"\(t, 3, H, W\)"):
        to_gray_uint8(clips[0, :, :1])


def test_identical_sets_score_zero_and_jitter_scores_higher(clips: torch.Tensor) -> None:
    same = FVMD().update(clips, real=True).update(clips, real=False).compute()
    assert same == pytest.approx(0.0, abs=1e-9)
    small = FVMD().update(clips, real=True).update(jitter(clips, 1, seed=1), real=False).compute()
    large = FVMD().update(clips, real=True).update(jitter(clips, 3, seed=1), real=False).compute()
    # real clips of another seed: the natural spread between two sets of real driving
    other = SyntheticClipDataset(num_clips=12, seed=8, height=64, width=112, clip_len=16, cameras=1)
    other_clips = torch.from_numpy(np.stack([other[i].frames[0] for i in range(12)])).float() / 127.5 - 1
    natural = FVMD().update(clips, real=True).update(other_clips, real=False).compute()
    assert natural < small < large, (natural, small, large)  # measured: 0.67 < 2.41 < 7.73
