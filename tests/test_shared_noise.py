"""Counterfactual token sampling: futures that share their Gumbel noise (ar_sampling.shared_gumbel)."""

from __future__ import annotations

import pytest
import torch

from gaia_app.diffusion.ar_sampling import AutoregressiveSampler, TokenPicker, shared_gumbel
from gaia_app.models.gaia1.world_model import WorldModel
from gaia_app.pipelines.gaia1_world_model import WorldModelRolloutPipeline, future_groups
from gaia_app.protocols.controllability import context_groups

V, T, M, N, E = 16, 4, 2, 6, 8
PROBS = torch.tensor([0.4, 0.25, 0.15, 0.1, 0.06, 0.04])


def frequencies(tokens: torch.Tensor, vocabulary: int) -> torch.Tensor:
    return torch.bincount(tokens, minlength=vocabulary).float() / len(tokens)


@pytest.mark.parametrize(("picker", "expected"), [
    (TokenPicker("sample"), PROBS),
    (TokenPicker("top_k", k=2), torch.tensor([0.4, 0.25, 0, 0, 0, 0]) / 0.65),
    (TokenPicker("top_p", p=0.7), torch.tensor([0.4, 0.25, 0.15, 0, 0, 0]) / 0.8),
    (TokenPicker("sample", temperature=2.0), PROBS.sqrt() / PROBS.sqrt().sum()),
], ids=["sample", "top_k", "top_p", "temperature"])
def test_gumbel_choice_draws_the_pickers_distribution(picker: TokenPicker, expected: torch.Tensor) -> None:
    """Handed independent Gumbel noise per row, every mode draws the distribution it draws without it."""
    rows = 40000
    logits = PROBS.log().repeat(rows, 1)
    generator = torch.Generator().manual_seed(0)
    drawn = picker(logits, gumbel=shared_gumbel(torch.arange(rows), len(PROBS), generator))
    torch.testing.assert_close(frequencies(drawn, len(PROBS)), expected, atol=0.012, rtol=0)


def test_rows_that_share_noise_pick_alike_where_their_logits_agree() -> None:
    generator = torch.Generator().manual_seed(1)
    logits = torch.randn(1, 50, generator=generator).repeat(4000, 1)
    groups = torch.arange(2000).repeat_interleave(2)  # rows 2i and 2i + 1 share noise
    drawn = TokenPicker("top_k", k=20)(logits, gumbel=shared_gumbel(groups, 50, generator)).view(-1, 2)
    assert (drawn[:, 0] == drawn[:, 1]).all()
    assert len(drawn[:, 0].unique()) > 10  # and the groups themselves draw differently
    # slightly different logits: still mostly the same token, unlike independent draws
    nudged = logits + 0.1 * torch.randn(logits.shape, generator=generator)
    coupled = TokenPicker("top_k", k=20)(nudged, gumbel=shared_gumbel(groups, 50, generator)).view(-1, 2)
    independent = TokenPicker("top_k", k=20)(nudged, generator).view(-1, 2)
    agree = lambda pair: (pair[:, 0] == pair[:, 1]).float().mean().item()  # noqa: E731
    assert agree(coupled) > 0.85 and agree(independent) < 0.3


def test_argmax_ignores_noise() -> None:
    logits = torch.tensor([[0.0, 3.0, 1.0]])
    assert TokenPicker("argmax")(logits, gumbel=torch.tensor([[9.0, 0.0, 0.0]])).item() == 1


@pytest.fixture(scope="module")
def net() -> WorldModel:
    torch.manual_seed(0)
    return WorldModel(V, dim=32, depth=2, heads=4, kv_heads=2, frames=T, text_tokens=M, image_tokens=N, text_dim=E,
                      action_shortcut=True).eval()


def rollouts(net: WorldModel, actions: torch.Tensor, groups: torch.Tensor | None, seed: int = 0) -> torch.Tensor:
    """Futures (b, 3, N) of one shared context under per-row actions (b, 5, 2)."""
    context = torch.randint(0, V, (1, 2, N), generator=torch.Generator().manual_seed(7)).repeat(len(actions), 1, 1)
    pipeline = WorldModelRolloutPipeline(net, AutoregressiveSampler(TokenPicker("top_k", k=8)))
    out = pipeline(context, 3, actions=actions, generator=torch.Generator().manual_seed(seed), noise_groups=groups)
    return out.tokens[:, 2:]


def test_one_context_under_one_command_with_shared_noise_gives_one_future(net: WorldModel) -> None:
    actions = torch.zeros(2, 5, 2)
    shared = rollouts(net, actions, torch.zeros(2, dtype=torch.long))
    assert torch.equal(shared[0], shared[1])
    assert not torch.equal(*rollouts(net, actions, None))  # independent draws part


def test_shared_noise_keeps_futures_under_other_commands_closer(net: WorldModel) -> None:
    """Two commands, 64 draws each: the futures of a pair agree on more tokens when they share their noise."""
    actions = torch.zeros(128, 5, 2)
    actions[1::2, 2:, 0] = 2.0  # odd rows: another speed from the first future step on
    pairs = torch.arange(64).repeat_interleave(2)
    agree = {name: (lambda x: (x[0::2] == x[1::2]).float().mean().item())(rollouts(net, actions, groups))
             for name, groups in (("shared", pairs), ("independent", None))}
    assert agree["shared"] > agree["independent"] + 0.2, agree


def test_future_groups_share_noise_future_by_future() -> None:
    assert future_groups(torch.tensor([0, 1, 0]), 2).tolist() == [0, 1, 2, 3, 0, 1]
    assert context_groups(commands=3, contexts=2).tolist() == [0, 1, 0, 1, 0, 1]


def test_noise_groups_must_be_one_per_rollout(net: WorldModel) -> None:
    with pytest.raises(ValueError, match=r"noise_groups: expected \(2,\) int64"):
        rollouts(net, torch.zeros(2, 5, 2), torch.zeros(3, dtype=torch.long))
    with pytest.raises(ValueError, match="noise_groups"):
        rollouts(net, torch.zeros(2, 5, 2), torch.tensor([0.0, 1.0]))
