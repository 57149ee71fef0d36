"""The synthetic world's public API: determinism, worker safety, the Clip contract, knobs and
the meaning of the ego actions."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gaia_app.data.clip import AGENT_CATEGORIES, DEFAULT_CAMERA_NAMES, Clip
from gaia_app.data.synthetic import SyntheticClipDataset, generate_clip
from gaia_app.data.synthetic.policy import integrate_pose

META_KEYS = {"source", "seed", "weather", "time_of_day", "country", "speed_limit", "lanes", "lane_types"}


@pytest.fixture(scope="module")
def clip() -> Clip:
    return generate_clip(seed=123, height=64, width=112, cameras=["front"], clip_len=8, fps=25.0)


def test_same_seed_same_clip_and_different_seeds_differ(clip: Clip) -> None:
    again = generate_clip(seed=123, height=64, width=112, cameras=["front"], clip_len=8, fps=25.0)
    other = generate_clip(seed=124, height=64, width=112, cameras=["front"], clip_len=8, fps=25.0)
    assert np.array_equal(clip.frames, again.frames)
    assert np.array_equal(clip.actions, again.actions) and clip.text == again.text and clip.meta == again.meta
    assert np.abs(clip.frames.astype(int) - other.frames.astype(int)).mean() > 10


def test_clip_contract(clip: Clip) -> None:
    assert clip.frames.shape == (1, 8, 3, 64, 112) and clip.frames.dtype == np.uint8
    assert np.allclose(np.diff(clip.timestamps), 1 / 25.0) and clip.fps == pytest.approx(25.0)
    assert clip.actions.shape == (8, 2) and np.all(clip.actions[:, 0] >= 0)
    assert META_KEYS <= clip.meta.keys() and clip.meta["source"] == "synthetic" and clip.meta["seed"] == 123
    assert len(clip.meta["lane_types"]) == clip.meta["lanes"] + 1
    assert len(clip.text) == 8 and all(isinstance(t, str) and t for t in clip.text)
    assert [c.name for c in clip.cameras] == ["front"] and clip.cameras[0].width == 112
    for boxes in clip.agents:
        assert np.all(boxes.category < len(AGENT_CATEGORIES)) and np.all(boxes.size > 0)
        assert np.all(np.linalg.norm(boxes.centre[:, :2], axis=1) < 100.0)
        assert np.allclose(boxes.centre[:, 2], boxes.size[:, 2] / 2)  # boxes stand on the ground


def test_dataset_is_deterministic_and_sized() -> None:
    ds = SyntheticClipDataset(num_clips=5, seed=7, clip_len=3)
    assert len(ds) == 5
    first = ds[3]
    assert np.array_equal(ds[1].frames, SyntheticClipDataset(num_clips=5, seed=7, clip_len=3)[1].frames)
    assert np.array_equal(first.frames, ds[3].frames) and first.clip_id == "synthetic-s7-000003"
    assert not np.array_equal(ds[2].frames, first.frames)
    with pytest.raises(IndexError):
        ds[5]


def test_dataset_is_worker_safe() -> None:
    """Clip i depends only on (seed, i): the same in the main process and in DataLoader workers,
    even when the global random state is disturbed."""
    ds = SyntheticClipDataset(num_clips=4, seed=3, clip_len=2, cameras=2)
    main = [ds[i] for i in range(4)]
    np.random.seed(99)
    torch.manual_seed(99)
    loader = torch.utils.data.DataLoader(ds, batch_size=None, num_workers=2, collate_fn=lambda clip: clip)
    for expected, got in zip(main, loader):
        assert got.clip_id == expected.clip_id
        assert np.array_equal(got.frames, expected.frames) and np.array_equal(got.actions, expected.actions)


def test_camera_count_and_names() -> None:
    clip = generate_clip(seed=1, cameras=5, clip_len=1)
    assert [c.name for c in clip.cameras] == list(DEFAULT_CAMERA_NAMES) and clip.frames.shape[0] == 5
    clip = generate_clip(seed=1, cameras=["rear_left", "front"], clip_len=1)
    assert [c.name for c in clip.cameras] == ["rear_left", "front"]


@pytest.mark.parametrize("kwargs,argument", [
    ({"height": 8}, "height"), ({"width": 12.5}, "width"), ({"cameras": 6}, "cameras"),
    ({"cameras": ["front", "roof"]}, "cameras"), ({"clip_len": 0}, "clip_len"), ({"fps": 0.0}, "fps"),
    ({"weather_mix": {"hail": 1.0}}, "weather_mix"), ({"time_of_day_mix": {"day": -1.0}}, "time_of_day_mix"),
    ({"agent_density": -0.5}, "agent_density"), ({"seed": -1}, "seed"),
])
def test_bad_arguments_name_the_argument(kwargs: dict, argument: str) -> None:
    with pytest.raises(ValueError, match=argument):
        generate_clip(**{"seed": 0, **kwargs})
    if argument != "seed":
        with pytest.raises(ValueError, match=argument):
            SyntheticClipDataset(num_clips=2, **kwargs)


def test_weather_and_time_of_day_mixes_are_obeyed() -> None:
    ds = SyntheticClipDataset(num_clips=12, seed=0, weather_mix={"snow": 1.0},
                              time_of_day_mix={"dusk": 2.0, "night": 0.0})
    described = [ds.describe(i) for i in range(len(ds))]
    assert {d["weather"] for d in described} == {"snow"} and {d["time_of_day"] for d in described} == {"dusk"}
    clip = ds[0]
    assert clip.meta["weather"] == "snow" and described[0]["lanes"] == clip.meta["lanes"]


def test_actions_integrate_to_the_logged_poses() -> None:
    """Action t (speed, curvature) held for 1/fps takes pose t exactly to pose t+1."""
    clip = generate_clip(seed=11, clip_len=12, fps=10.0)
    poses = np.array([m["ego_pose"] for m in clip.frame_meta])
    for t in range(11):
        x, y, yaw = integrate_pose(*poses[t], *clip.actions[t], 0.1)
        assert np.allclose([x, y, yaw], poses[t + 1], atol=2e-3)


def test_speed_and_curvature_are_diverse() -> None:
    """The behaviour policies cover stops, city and highway speeds, both turning directions."""
    ds = SyntheticClipDataset(num_clips=48, seed=5, clip_len=16)
    rows = [ds.describe(i) for i in range(len(ds))]
    speed = np.array([r["speed"] for r in rows])
    curvature = np.array([r["curvature"] for r in rows])
    assert speed.min() < 3.0 and speed.max() > 20.0 and speed.std() > 5.0
    assert curvature.min() < -0.01 and curvature.max() > 0.01
    assert len({r["behaviour"] for r in rows}) == 6 and len({r["environment"] for r in rows}) == 4


def test_open_loop_clips_switch_to_a_constant_command_in_the_same_scene() -> None:
    """driven_share: the chosen clips keep their scene and their policy's first quarter, then hold one command from
    the moment meta.command_start_s says."""
    driven = SyntheticClipDataset(num_clips=8, seed=5, height=16, width=16, clip_len=24, driven_share=0.5)
    policy = SyntheticClipDataset(num_clips=8, seed=5, height=16, width=16, clip_len=24)
    flags = [bool(driven[i].meta.get("open_loop")) for i in range(8)]
    assert 0 < sum(flags) < 8
    for i, open_loop in enumerate(flags):
        mine, theirs = driven[i], policy[i]
        assert mine.meta["weather"] == theirs.meta["weather"] and mine.meta["lanes"] == theirs.meta["lanes"]
        np.testing.assert_array_equal(mine.actions[:6], theirs.actions[:6])  # the switch is in the middle half
        if open_loop:
            curvature, speed = mine.actions[-6:, 1], mine.actions[-6:, 0]
            assert ((np.ptp(curvature) == 0 and np.allclose(np.diff(speed), np.diff(speed)[0], atol=1e-4))
                    or speed.min() == 0)
            assert not np.array_equal(mine.actions, theirs.actions)
            # meta.command_start_s: the first frame that leaves the policy
            start = round(mine.meta["command_start_s"] * 25.0)
            np.testing.assert_array_equal(mine.actions[:start], theirs.actions[:start])
            assert not np.array_equal(mine.actions[start], theirs.actions[start])
        else:
            np.testing.assert_array_equal(mine.actions, theirs.actions)
            assert "command_start_s" not in mine.meta
    with pytest.raises(ValueError, match="driven_share"):
        SyntheticClipDataset(num_clips=1, driven_share=1.5)


def test_open_loop_acceleration_range_sets_the_commands() -> None:
    """open_loop_acceleration: every open-loop command accelerates within the given range, and the range is checked."""
    fps = 6.25
    rates = []
    for low, high in ((3.0, 4.0), (-5.0, -4.0)):
        ds = SyntheticClipDataset(num_clips=6, seed=2, height=16, width=16, clip_len=16, fps=fps, driven_share=1.0,
                                  open_loop_acceleration=[low, high])
        for i in range(len(ds)):
            speed = ds[i].actions[-4:, 0]
            if 0.0 < speed.min() and speed.max() < 30.0:  # not clipped at a stop or at the speed cap
                rate = float(np.diff(speed).mean() * fps)
                assert low - 1e-3 <= rate <= high + 1e-3, (low, high, rate)
                rates.append(rate)
    assert min(rates) < 0 < max(rates)
    for bad in ([2.0, 1.0], [0.0], "fast", [0.0, float("nan")]):
        with pytest.raises(ValueError, match="open_loop_acceleration"):
            SyntheticClipDataset(num_clips=1, open_loop_acceleration=bad)


@pytest.mark.parametrize("rate", [6.25, 10.0])
def test_render_rate_renders_only_what_resampling_keeps(rate: float) -> None:
    """A world rendered at `render_rate` gives exactly the full clip resampled to that rate: frames, actions,
    timestamps, captions, agents and labels (a whole and a non-whole ratio of the 25 Hz simulation)."""
    from gaia_app.data.transforms import resample_clip

    kwargs = dict(num_clips=2, seed=9, height=32, width=48, clip_len=13, weather_mix={"rain": 1.0}, driven_share=1.0)
    full = resample_clip(SyntheticClipDataset(**kwargs)[1], rate)
    cheap = SyntheticClipDataset(**kwargs, render_rate=rate)[1]
    assert cheap.frames.shape == full.frames.shape and full.frames.shape[1] < 13
    assert np.array_equal(cheap.frames, full.frames)  # rain streaks included: they are seeded per simulation step
    assert np.array_equal(cheap.actions, full.actions) and np.allclose(cheap.timestamps, full.timestamps)
    assert cheap.text == full.text and cheap.meta == full.meta
    fields = ("centre", "size", "yaw", "category", "track_id")
    assert len(cheap.agents) == len(full.agents)
    assert all(np.array_equal(getattr(a, f), getattr(b, f)) for a, b in zip(cheap.agents, full.agents) for f in fields)
    assert repr(cheap.frame_meta) == repr(full.frame_meta)


@pytest.mark.parametrize("render_rate", [0.0, -1.0, 50.0, float("nan")])
def test_render_rate_outside_the_simulation_rate_is_refused(render_rate: float) -> None:
    with pytest.raises(ValueError, match="render_rate"):
        SyntheticClipDataset(num_clips=1, fps=25.0, render_rate=render_rate)


def test_cached_clips_are_the_rendered_clips_and_the_oldest_leaves_first() -> None:
    cached = SyntheticClipDataset(num_clips=4, seed=3, height=32, width=48, clip_len=2, cache_clips=2)
    plain = SyntheticClipDataset(num_clips=4, seed=3, height=32, width=48, clip_len=2)
    first = cached.sample(0)
    assert cached.sample(0) is first and cached.sample(-4) is first  # read again, not re-rendered
    np.testing.assert_array_equal(first.clip.frames, plain[0].frames)
    cached.sample(1), cached.sample(0), cached.sample(2)  # 1 is now the least recently read: it leaves
    assert list(cached.cached) == [0, 2] and cached.sample(1) is not first
    assert plain.cached == {} and plain.sample(0) is not plain.sample(0)
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="cache_clips"):
            SyntheticClipDataset(num_clips=4, cache_clips=bad)
