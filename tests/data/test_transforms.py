"""Transforms: resampling by timestamps, resizing that keeps intrinsics true, pixel scaling, windows."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gaia_app.data.clip import CameraSpec, Clip, ClipError
from gaia_app.data.transforms import (
    resample_clip,
    resample_indices,
    resize_clip,
    to_float,
    to_uint8,
    window_indices,
)


def brute_nearest(t: np.ndarray, hz: float) -> np.ndarray:
    ticks = np.arange(t[0], t[-1] + 1e-9, 1 / hz)
    return np.abs(t[None, :] - ticks[:, None]).argmin(axis=1)


def test_25_to_6_25_hz_takes_every_4th_frame():
    t = np.arange(221) / 25
    np.testing.assert_array_equal(resample_indices(t, 6.25), np.arange(0, 221, 4))
    assert len(resample_indices(t, 6.25)) == 56


@pytest.mark.parametrize("source_hz", [30, 20, 10, 12.5])
def test_other_rates_pick_the_nearest_frame_to_each_tick(source_hz):
    t = 3.7 + np.arange(int(8 * source_hz)) / source_hz
    picked = resample_indices(t, 6.25)
    np.testing.assert_array_equal(picked, brute_nearest(t, 6.25))
    assert np.all(np.abs(t[picked] - (t[0] + np.arange(len(picked)) * 0.16)) <= 0.5 / source_hz + 1e-9)


def test_jittered_timestamps_and_same_rate():
    rng = np.random.default_rng(0)
    t = np.arange(100) / 25 + rng.uniform(-0.004, 0.004, 100)
    np.testing.assert_array_equal(resample_indices(t, 6.25), np.arange(0, 100, 4))
    np.testing.assert_array_equal(resample_indices(np.arange(50) / 10, 10), np.arange(50))


def test_upsampling_is_refused_naming_both_rates():
    with pytest.raises(ClipError, match="cannot resample to 25 Hz: the source runs at only 10 Hz"):
        resample_indices(np.arange(20) / 10, 25)


def test_resample_clip_keeps_labels_with_their_frames(clip_factory):
    clip = clip_factory(t=8, fps=10.0)
    half = resample_clip(clip, 5.0)
    np.testing.assert_array_equal(half.timestamps, clip.timestamps[::2])
    np.testing.assert_array_equal(half.actions, clip.actions[::2])
    assert half.text == clip.text[::2] and half.frames.shape[1] == 4


def test_window_indices():
    np.testing.assert_array_equal(window_indices(7, 3, 2), [[0, 1, 2], [2, 3, 4], [4, 5, 6]])
    assert window_indices(2, 3, 1).shape == (0, 3)


def dot_clip(point_cam: np.ndarray, w: int = 320, h: int = 180) -> tuple[Clip, CameraSpec]:
    """A one-frame clip whose image shows a bright dot where the camera sees `point_cam` (camera frame, m)."""
    cam = CameraSpec("front", [[250.0, 0, 150.0], [0, 240.0, 95.0], [0, 0, 1]], np.eye(4), w, h)
    u, v = project(cam, point_cam)
    frames = np.zeros((1, 1, 3, h, w), np.uint8)
    yy, xx = np.mgrid[0:h, 0:w]
    # the pixel (i, j) covers [j, j+1) x [i, i+1): its centre is at (j + 0.5, i + 0.5)
    frames[0, 0, :, (xx + 0.5 - u) ** 2 + (yy + 0.5 - v) ** 2 <= 16] = 255
    return Clip("dot", frames, [0.0], cameras=[cam]), cam


def project(cam: CameraSpec, point_cam: np.ndarray) -> np.ndarray:
    p = cam.intrinsics @ point_cam
    return p[:2] / p[2]


def dot_centre(frame_chw: np.ndarray) -> np.ndarray:
    yy, xx = np.mgrid[0 : frame_chw.shape[1], 0 : frame_chw.shape[2]]
    weight = frame_chw[0].astype(float)
    return np.array([(weight * (xx + 0.5)).sum(), (weight * (yy + 0.5)).sum()]) / weight.sum()


@pytest.mark.parametrize(("height", "width", "mode"), [(64, 64, "crop"), (90, 200, "crop"), (64, 96, "stretch")])
def test_resize_updates_intrinsics_so_points_land_on_their_pixel(height, width, mode):
    point = np.array([0.6, -0.2, 4.0])  # right of and above the optical axis, 4 m ahead
    clip, _ = dot_clip(point)
    small = resize_clip(clip, height, width, mode)
    cam = small.cameras[0]
    assert small.frames.shape == (1, 1, 3, height, width) and (cam.width, cam.height) == (width, height)
    np.testing.assert_allclose(dot_centre(small.frames[0, 0]), project(cam, point), atol=0.3)


def test_crop_mode_preserves_aspect():
    clip, cam = dot_clip(np.array([0.0, 0.0, 1.0]))
    square = resize_clip(clip, 90, 90, "crop").cameras[0].intrinsics
    # 320x180 -> scale 0.5 to 160x90, crop 35 px from the left: focal lengths halve alike
    np.testing.assert_allclose(square[[0, 1, 0, 1], [0, 1, 2, 2]], [125.0, 120.0, 75.0 - 35.0, 47.5])


def test_pixel_scaling_round_trip():
    pixels = torch.arange(256, dtype=torch.uint8)
    x = to_float(pixels.numpy())
    assert x.dtype == torch.float32 and x.min() == -1 and x.max() == 1
    assert torch.equal(to_uint8(x), pixels)
    assert to_uint8(torch.tensor([-3.0, 2.0])).tolist() == [0, 255]  # clamped
    with pytest.raises(TypeError, match="uint8"):
        to_float(np.zeros(3, np.float32))
