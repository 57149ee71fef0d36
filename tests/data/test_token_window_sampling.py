"""Where GAIA-1 training windows of a token cache start: uniformly, or where the ego's command changes
(token_cache.TokenWindows, data.window_sampling=action_change)."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import torch

from gaia_app.data.clip import ClipError
from gaia_app.data.datamodules import TokenCacheDataModule
from gaia_app.data.token_cache import TokenSegment, TokenWindows, segment_commands, token_action_change_weights

STEPS, SEQ, AFTER = 20, 12, 4  # steps per segment, window, context steps before the change


def braking_segment(name: str, onset: int | None, actions: bool = True) -> TokenSegment:
    """STEPS steps at 20 m/s, braking by 0.6 m/s per step from step `onset` on (None: steady throughout). Each step's
    tokens hold the step's index, so a window tells where it starts."""
    speed = np.full(STEPS, 20.0, np.float32)
    if onset is not None:
        speed[onset:] -= 0.6 * np.arange(1, STEPS - onset + 1)
    tokens = np.broadcast_to(np.arange(STEPS)[:, None], (STEPS, 6)).copy()
    return TokenSegment(name=name, tokens=tokens,
                        actions=np.stack([speed, np.zeros(STEPS, np.float32)], 1) if actions else None)


def drawn_starts(windows: TokenWindows, index: int, draws: int = 400) -> Counter:
    torch.manual_seed(0)
    return Counter(int(windows[index]["tokens"][0, 0]) for _ in range(draws))


def test_commands_are_the_speed_change_per_step_and_the_curvature() -> None:
    commands = segment_commands(braking_segment("b", 10).actions)
    np.testing.assert_allclose(commands[:10, 0], 0.0)
    np.testing.assert_allclose(commands[10:, 0], -0.6, atol=1e-5)  # a constant braking: a constant change


def test_the_window_whose_generated_steps_begin_at_the_onset_is_drawn_most() -> None:
    segments = [braking_segment("brakes_at_10", 10), braking_segment("steady", None)]
    spans = [(0, 0, STEPS), (1, 0, STEPS)]
    weights = token_action_change_weights(segments, spans, SEQ, AFTER)
    brakes, steady = (w.numpy() for w in weights)
    assert brakes.shape == steady.shape == (STEPS - SEQ + 1,)
    np.testing.assert_allclose([brakes.sum(), steady.sum()], 1.0)
    # start 6 puts the onset (step 10) at the window's step 4, the first one after the context
    assert int(brakes.argmax()) == 10 - AFTER
    np.testing.assert_allclose(steady, 1 / len(steady))  # no change anywhere: uniform starts

    windows = TokenWindows(segments, spans, SEQ, 1, "action_change", AFTER)
    assert len(windows) == 2 * (STEPS - SEQ + 1)  # as many items as uniform windows: each span visited as often
    drawn = drawn_starts(windows, 0)
    assert drawn.most_common(1)[0][0] == 10 - AFTER and drawn[10 - AFTER] > 0.2 * 400  # uniform: 1 of 9 starts
    # items of the second span stay in the second span (its tokens are the steps', its actions steady)
    item = windows[len(windows) - 1]
    assert float(item["actions"][:, 0].std()) == 0.0


def test_uniform_windows_are_unchanged() -> None:
    segments = [braking_segment("brakes_at_10", 10)]
    windows = TokenWindows(segments, [(0, 0, STEPS)], SEQ, 1)
    assert windows.start_weights is None
    assert [int(windows[i]["tokens"][0, 0]) for i in range(len(windows))] == list(range(STEPS - SEQ + 1))


def test_bad_sampling_settings_are_named() -> None:
    segments = [braking_segment("no_actions", 10, actions=False)]
    with pytest.raises(ClipError, match="no_actions.*actions"):
        TokenWindows(segments, [(0, 0, STEPS)], SEQ, 1, "action_change", AFTER)
    with pytest.raises(ValueError, match="change_after=12"):
        TokenWindows([braking_segment("b", 10)], [(0, 0, STEPS)], SEQ, 1, "action_change", SEQ)
    with pytest.raises(ValueError, match="window_sampling='onsets'"):
        TokenWindows([braking_segment("b", 10)], [(0, 0, STEPS)], SEQ, 1, "onsets", AFTER)


def test_the_datamodule_samples_training_windows_at_changes_and_validates_uniformly(tmp_path: Path) -> None:
    for k in range(4):
        segment = braking_segment(f"seg{k}", 8 + k)
        np.save(tmp_path / f"seg{k}.npy", segment.tokens)
        np.save(tmp_path / f"seg{k}.actions.npy", segment.actions)
    dm = TokenCacheDataModule(str(tmp_path), seq_len=SEQ, val_fraction=0.25, batch_size=2,
                              window_sampling="action_change", change_after=AFTER)
    dm.setup()
    assert dm.train_set.start_weights is not None and dm.val_set.start_weights is None
    torch.manual_seed(0)
    loader = dm.train_dataloader()
    speeds = [speed for _ in range(100) for speed in next(iter(loader))["actions"][..., 0]]
    onsets = [int((speed < 20.0).float().argmax()) for speed in speeds]
    # the onset sits at the window's step 3..5 in 3 of 9 uniform windows; ∝ the change squared in about 0.6 of them
    assert np.mean([3 <= p <= 5 for p in onsets]) > 0.45


def test_token_window_onsets_gives_the_expected_contrast_under_each_sampling(tmp_path: Path) -> None:
    """benchmarks/token_window_onsets.py: one segment braking 0.6 m/s per step from step 10, one steady. The braking
    segment's 9 uniform windows hold the onset at their steps 10 − s; the expected contrast of the change per step is
    the mean over them (exact, from the start probabilities), the action_change one weighs them by its square."""
    from tests.conftest import load_benchmark

    onsets = load_benchmark("token_window_onsets")
    for name, onset in (("a_brakes", 10), ("b_steady", None), ("c_val", 10)):
        segment = braking_segment(name, onset)
        np.save(tmp_path / f"{name}.npy", segment.tokens)
        np.save(tmp_path / f"{name}.actions.npy", segment.actions)
    result = onsets.main(["--tokens", str(tmp_path), "--val-fraction", "0.34", "--out", str(tmp_path)])
    assert result["training_spans"] == 2
    position = np.arange(10, 10 - (STEPS - SEQ + 1), -1)  # the onset's step in the window starting at 0..8
    contrast = np.where(position >= AFTER, 0.6 * (SEQ - position) / (SEQ - AFTER), 0.6 * position / AFTER)
    speed = "speed change per step (m/s)"
    uniform, changed = result["expected_contrast"]["uniform"], result["expected_contrast"]["action_change"]
    assert uniform[speed] == pytest.approx(contrast.mean() / 2, rel=1e-4)  # the steady span adds 0
    assert changed[speed] == pytest.approx((contrast ** 3).sum() / (contrast ** 2).sum() / 2, rel=1e-4)
    assert uniform["curvature (1/m)"] == changed["curvature (1/m)"] == 0.0
    assert (tmp_path / "onsets.json").exists()
