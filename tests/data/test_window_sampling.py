"""Where training windows of a latent cache start: uniformly, or where the ego's action changes (latent_windows.py)."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import torch

from gaia_app.data.clip import ClipError
from gaia_app.data.latent_cache import LatentClip, find_latent_clips, write_latent_clip
from gaia_app.data.latent_windows import (
    LatentCacheDataModule,
    LatentWindows,
    action_change_weights,
    action_changes,
    step_commands,
)
from gaia_app.data.metadata import MetadataEncoder

STEPS, TAU = 8, 4  # latent steps per clip, frames per step


def clip_with_turn(clip_id: str, turn_step: int | None, actions: bool = True) -> LatentClip:
    """A one-camera clip of STEPS latent steps at 10 m/s, straight until latent step `turn_step` (None: straight
    throughout), then a 0.02 1/m curve. Its latents hold their step's index, so a window tells where it starts."""
    frames = STEPS * TAU
    curvature = np.zeros(frames, np.float32)
    if turn_step is not None:
        curvature[turn_step * TAU:] = 0.02
    step_index = np.broadcast_to(np.arange(STEPS, dtype=np.float32)[None, :, None, None, None], (1, STEPS, 4, 2, 3))
    return LatentClip(clip_id=clip_id, mean=step_index.copy(),
                      logvar=np.zeros((1, STEPS, 4, 2, 3), np.float32), temporal_downsampling=TAU, fps=12.5,
                      image_size=(16, 24), timestamps=np.arange(frames) / 12.5, cameras=None, meta={},
                      actions=np.stack([np.full(frames, 10.0, np.float32), curvature], 1) if actions else None)


@pytest.fixture()
def cache(tmp_path: Path) -> Path:
    for split in ("train", "val"):
        write_latent_clip(tmp_path / split, clip_with_turn("turns_at_5", 5))
        write_latent_clip(tmp_path / split, clip_with_turn("straight", None))
    return tmp_path


def drawn_starts(windows: LatentWindows, index: int, draws: int = 400) -> Counter:
    torch.manual_seed(0)
    return Counter(int(windows[index]["mean"][0, 0].max()) for _ in range(draws))


def test_action_changes_measure_the_change_after_the_context() -> None:
    commands = step_commands(clip_with_turn("c", 5))
    np.testing.assert_allclose(commands[:, 0], 0.0)  # a steady 10 m/s: no acceleration
    change = action_changes(commands, steps=4, change_after=2, spread=np.array([1.0, 0.01]))
    # starts 0..4; the turn at step 5 is after the context (steps s, s+1) and inside the window for s = 2 (once) and
    # s = 3 (twice: both generated steps turned); s = 4 has it in its context (one of two steps), so a change too
    np.testing.assert_allclose(change, [0.0, 0.0, 1.0, 2.0, 1.0], atol=1e-6)


def test_a_constant_braking_weighs_its_onset_not_the_windows_after_it() -> None:
    """A 12-step clip braking at 4 m/s² from latent step 5 on: its speed falls in every later window, its command
    (acceleration) changes only around the onset, so the windows wholly after it are never drawn."""
    frames, onset = 12 * TAU, 5 * TAU
    speed = 10.0 - 4.0 * np.clip(np.arange(frames) - onset + 1, 0, None) / 12.5
    clip = LatentClip(clip_id="brakes", mean=np.zeros((1, 12, 4, 2, 3), np.float32),
                      logvar=np.zeros((1, 12, 4, 2, 3), np.float32), temporal_downsampling=TAU, fps=12.5,
                      image_size=(16, 24), timestamps=np.arange(frames) / 12.5, cameras=None, meta={},
                      actions=np.stack([speed, np.zeros(frames)], 1).astype(np.float32))
    np.testing.assert_allclose(step_commands(clip)[6:, 0], -4.0, atol=1e-4)
    weights = action_change_weights([clip], steps=4, change_after=2)[0]
    assert int(weights.argmax()) == 3 and float(weights[6:].sum()) < 1e-4  # starts 6–8 lie wholly after the onset


def test_action_change_sampling_starts_where_the_action_changes(cache: Path) -> None:
    clips = find_latent_clips(cache / "train")
    index = [c.name for c in clips].index("turns_at_5")
    uniform = LatentWindows(clips, 4, MetadataEncoder([]), window_sampling="uniform")
    changed = LatentWindows(clips, 4, MetadataEncoder([]), window_sampling="action_change", change_after=2)
    on_change = drawn_starts(changed, index)
    assert set(on_change) == {2, 3, 4}  # never a window whose 4 steps all drive straight
    assert on_change[3] > 2.5 * on_change[2] and on_change[3] > 2.5 * on_change[4]  # ∝ the change squared: 1 : 4 : 1
    assert set(drawn_starts(uniform, index)) == {0, 1, 2, 3, 4}
    # a clip whose action never changes keeps uniform starts
    straight = [c.name for c in clips].index("straight")
    torch.testing.assert_close(changed.start_weights[straight], torch.full((5,), 0.2, dtype=torch.float64))


def test_datamodule_passes_the_sampling_to_training_windows_only(cache: Path) -> None:
    dm = LatentCacheDataModule(str(cache), steps=4, window_sampling="action_change", change_after=1)
    dm.setup("fit")
    assert dm.train_set.start_weights is not None and dm.val_set.start_weights is None


def test_train_meta_keeps_the_matching_training_clips_and_every_validation_clip(tmp_path: Path) -> None:
    """data.train_meta={open_loop: true} trains on the clips driven off their policy alone (the onset arm's data)."""
    for split in ("train", "val"):
        for name, meta in (("driven", {"open_loop": True, "weather": "rain"}), ("policy", {"weather": "rain"})):
            clip = clip_with_turn(f"{split}_{name}", 5)
            clip.meta = meta
            write_latent_clip(tmp_path / split, clip)
    dm = LatentCacheDataModule(str(tmp_path), steps=4, train_meta={"open_loop": True})
    dm.setup("fit")
    assert [c.clip_id for c in dm.train_set.clips] == ["train_driven"]
    assert sorted(c.clip_id for c in dm.val_set.clips) == ["val_driven", "val_policy"]
    everything = LatentCacheDataModule(str(tmp_path), steps=4)
    everything.setup("fit")
    assert len(everything.train_set) == 2
    with pytest.raises(ClipError, match=r"\['open_lop'\] appear in no clip's meta under .*train"):
        LatentCacheDataModule(str(tmp_path), steps=4, train_meta={"open_lop": True}).setup("fit")
    with pytest.raises(ClipError, match=r"train_meta=\{'weather': 'snow'\}: none of the 2 clips"):
        LatentCacheDataModule(str(tmp_path), steps=4, train_meta={"weather": "snow"}).setup("fit")


def test_the_onset_experiment_selects_the_open_loop_clips(tmp_path: Path) -> None:
    from tests.conftest import compose_config

    cfg = compose_config("train", ["experiment=gaia2/road_users/world_model_s4_paper_onsets"], tmp_path)
    assert dict(cfg.data.train_meta) == {"open_loop": True} and cfg.data.window_sampling == "action_change"


def test_bad_sampling_settings_are_named(cache: Path, tmp_path: Path) -> None:
    clips = find_latent_clips(cache / "train")
    with pytest.raises(ValueError, match="window_sampling='onsets'"):
        LatentWindows(clips, 4, MetadataEncoder([]), window_sampling="onsets")
    with pytest.raises(ValueError, match=r"change_after=4: expected .* \[1, steps − 1 = 3\]"):
        LatentWindows(clips, 4, MetadataEncoder([]), window_sampling="action_change", change_after=4)
    write_latent_clip(tmp_path / "bare", clip_with_turn("no_actions", None, actions=False))
    with pytest.raises(ClipError, match="no_actions"):
        LatentWindows(find_latent_clips(tmp_path / "bare"), 4, MetadataEncoder([]), window_sampling="action_change")


def test_window_onsets_counts_the_windows_whose_generated_steps_hold_the_command_onset(tmp_path: Path) -> None:
    """benchmarks/window_onsets.py: a clip whose command starts at latent step 5 (frame 20) has it in the generated
    steps (2, 3) of the windows starting at steps 2 and 3, in the last context step of the one starting at 4: 2 and 1
    of 5 uniform starts; under action_change the starts 2, 3, 4 weigh 1 : 4 : 1 (the change squared)."""
    from tests.conftest import load_benchmark

    onsets = load_benchmark("window_onsets")
    turning = clip_with_turn("turns_at_5", 5)
    turning.meta = {"open_loop": True, "command_start_s": 20 / 12.5}
    write_latent_clip(tmp_path / "train", turning)
    write_latent_clip(tmp_path / "train", clip_with_turn("straight", None))
    result = onsets.main(["--cache", str(tmp_path), "--steps", "4", "--change-after", "2", "--out", str(tmp_path)])
    assert result["clips"] == 2 and result["open_loop_clips"] == 1
    uniform, changed = result["shares"]["uniform"], result["shares"]["action_change"]
    assert uniform["generated steps"]["open-loop clips' windows"] == pytest.approx(2 / 5)
    assert uniform["last context step"]["open-loop clips' windows"] == pytest.approx(1 / 5)
    assert uniform["generated steps"]["all windows"] == pytest.approx(1 / 5)  # the policy clip holds none
    assert changed["generated steps"]["open-loop clips' windows"] == pytest.approx(5 / 6)
    assert changed["last context step"]["open-loop clips' windows"] == pytest.approx(1 / 6)
    assert "| action_change | 0.417 | 0.833 | 0.083 | 0.167 |" in (tmp_path / "window_onsets.md").read_text()
    turning.meta = {"open_loop": True}
    write_latent_clip(tmp_path / "bare" / "train", turning)
    with pytest.raises(ClipError, match="turns_at_5.*command_start_s"):
        onsets.main(["--cache", str(tmp_path / "bare")])
