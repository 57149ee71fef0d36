"""GAIA-1 Fig. 4: the video decoder's training tasks as context/token masks."""

from __future__ import annotations

import pytest
import torch

from gaia_app.models.gaia1.decoder_tasks import TASKS, TaskSampler, drop_tokens, make_task

T = 7


def bools(s: str) -> torch.Tensor:
    return torch.tensor([c == "1" for c in s])


@pytest.mark.parametrize(("name", "context", "tokens", "temporal"), [
    ("image", "0000000", "1111111", False),
    ("video", "0000000", "1111111", True),
    ("forward", "1100000", "0011111", True),
    ("backward", "0000011", "1111100", True),
    ("interpolation", "1010101", "0000000", True),
])
def test_each_task_builds_the_fig4_masks(name: str, context: str, tokens: str, temporal: bool) -> None:
    task = make_task(name, T, context=2)
    assert torch.equal(task.context, bools(context)) and torch.equal(task.tokens, bools(tokens))
    assert task.temporal is temporal
    assert torch.equal(task.target, ~bools(context))
    # tokens are only ever given for frames that are generated, never for context frames
    assert not (task.tokens & task.context).any()


def test_tasks_are_drawn_with_equal_probability() -> None:
    sampler = TaskSampler({name: 1.0 for name in TASKS}, T)
    g = torch.Generator().manual_seed(0)
    counts = {name: 0 for name in TASKS}
    for _ in range(5000):
        counts[sampler(g).name] += 1
    assert all(abs(c / 5000 - 0.2) < 0.025 for c in counts.values()), counts


def test_bad_task_settings_are_named() -> None:
    with pytest.raises(ValueError, match="flip"):
        make_task("flip", T)
    with pytest.raises(ValueError, match="context=7"):
        make_task("forward", T, context=7)
    with pytest.raises(ValueError, match="task probabilities"):
        TaskSampler({"video": -1.0}, T)


def test_token_dropout_rate() -> None:
    mask = torch.ones(8, 7, 16, 28, dtype=torch.bool)
    kept = drop_tokens(mask, 0.15, torch.Generator().manual_seed(0))
    assert abs(1 - kept.float().mean().item() - 0.15) < 0.01
    assert not drop_tokens(torch.zeros_like(mask), 0.15).any()  # never adds tokens
