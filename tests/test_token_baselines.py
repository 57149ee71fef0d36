"""Baselines of the world-model evaluation: unigram and smoothed copy-previous-frame cross-entropies."""

from __future__ import annotations

import math

import pytest
import torch

from gaia_app.eval.token_baselines import (
    copy_previous_cross_entropy,
    model_cross_entropy,
    unigram_cross_entropy,
)


def test_unigram_of_uniform_tokens_is_log_vocab() -> None:
    train = torch.arange(8).repeat(100)
    assert unigram_cross_entropy(train, torch.arange(8), 8) == pytest.approx(math.log(8), rel=1e-6)


def test_copy_previous_picks_the_mismatch_rate() -> None:
    tokens = torch.zeros(1, 5, 4, dtype=torch.long)
    tokens[0, 2, 0] = 3  # 2 of 16 scored tokens differ from the previous frame
    ce, eps = copy_previous_cross_entropy(tokens, 16)
    assert eps == pytest.approx(2 / 16)
    assert ce == pytest.approx(-(14 / 16 * math.log(14 / 16) + 2 / 16 * math.log(2 / 16 / 15)))
    static = torch.ones(2, 3, 4, dtype=torch.long)
    assert copy_previous_cross_entropy(static, 16)[0] < 1e-4


def test_model_cross_entropy_scores_frames_after_the_first_in_chunks() -> None:
    """Uniform logits give log V per token whatever the chunking; a model sure of the true tokens gives ~0."""
    windows = torch.randint(0, 8, (5, 3, 4), generator=torch.Generator().manual_seed(0))
    uniform = model_cross_entropy(lambda x: torch.zeros(*x.shape, 8), windows, batch=2)
    assert uniform == pytest.approx(math.log(8), rel=1e-6)
    assert model_cross_entropy(lambda x: 50.0 * torch.nn.functional.one_hot(x, 8).float(), windows) < 1e-6
