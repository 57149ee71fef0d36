"""GAIA-1 Fig. 6 (§5.1): per-position perplexity of real, argmax, sampled and top-k frames; its PNG and Rerun
outputs."""

from __future__ import annotations

import math

import pytest
import torch
from einops import rearrange
from PIL import Image
from rerun.chunk import RrdReader

from gaia_app.eval.token_perplexity import (
    STRATEGIES,
    FramePerplexity,
    frame_perplexity,
    mean_curves,
    null_conditions,
    summarize,
    token_log_perplexity,
)
from gaia_app.models.gaia1.world_model import Conditions, WorldModel
from gaia_app.viz.plots import LOG_ROOT, POSITION, ROOT, save_figure, save_token_perplexity_rrd, token_perplexity_figure

V, T, M, N, E, B, K = 32, 3, 2, 8, 8, 3, 4


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def net() -> WorldModel:
    torch.manual_seed(0)
    net = WorldModel(V, dim=32, depth=2, heads=4, kv_heads=2, frames=T, text_tokens=M, image_tokens=N,
                     text_dim=E).eval()
    with torch.no_grad():  # a peaked distribution, as a trained model has: random init is nearly uniform
        net.head.weight.mul_(20.0)
    return net


@pytest.fixture(scope="module")
def data(net: WorldModel) -> tuple[torch.Tensor, torch.Tensor, Conditions]:
    """Context (B, T - 1, N), real frame (B, N) and text/action conditions for T steps."""
    g = torch.Generator().manual_seed(1)
    context, real = torch.randint(0, V, (B, T - 1, N), generator=g), torch.randint(0, V, (B, N), generator=g)
    cond = net.conditioner(B, T, torch.randn(B, T, M, E, generator=g), torch.randn(B, T, 2, generator=g))
    return context, real, cond


@pytest.fixture(scope="module")
def result(net: WorldModel, data) -> FramePerplexity:
    context, real, cond = data
    return frame_perplexity(net, context, real, cond, k=K, generator=torch.Generator().manual_seed(2))


def teacher_forced_log_probs(net: WorldModel, context: torch.Tensor, frame: torch.Tensor,
                             cond: Conditions) -> torch.Tensor:
    """log p(· | context, frame_<i) for every position i: (b, n, V), from one plain forward."""
    with torch.no_grad():
        return net(torch.cat([context, frame[:, None]], dim=1), cond)[:, -1].log_softmax(-1)


def test_shapes_and_ranges(result: FramePerplexity) -> None:
    assert tuple(result.tokens) == STRATEGIES and tuple(result.log_ppl) == STRATEGIES
    for name in STRATEGIES:
        assert result.tokens[name].shape == (B, N) and result.log_ppl[name].shape == (B, N)
        assert result.tokens[name].min() >= 0 and result.tokens[name].max() < V
        assert (result.log_ppl[name] >= 0).all()  # p ≤ 1 → ppl ≥ 1
    stats = result.summary()["real"]
    assert set(stats) == {"mean_log_ppl", "ppl", "median_ppl", "max_ppl", "frac_ppl_below_1_5", "std_log_ppl"}


def test_real_ppl_is_exp_cross_entropy(net: WorldModel, data, result: FramePerplexity) -> None:
    context, real, cond = data
    with torch.no_grad():
        logits = net(torch.cat([context, real[:, None]], dim=1), cond)[:, -1]
    ce = torch.nn.functional.cross_entropy(rearrange(logits, "b n v -> b v n"), real, reduction="none")
    torch.testing.assert_close(result.ppl["real"], ce.exp())


def test_argmax_ppl_is_the_minimum_given_its_prefix(net: WorldModel, data, result: FramePerplexity) -> None:
    """At every position argmax has the lowest perplexity possible given its own prefix (teacher forcing)."""
    context, _, cond = data
    log_p = teacher_forced_log_probs(net, context, result.tokens["argmax"], cond)
    assert torch.equal(result.tokens["argmax"], log_p.argmax(-1))
    torch.testing.assert_close(result.log_ppl["argmax"], -log_p.max(-1).values)
    # the first token has the same prefix (the context) in every frame, so there argmax ≤ everyone;
    # later positions have different prefixes per strategy, and nothing orders them
    for name in STRATEGIES:
        assert (result.log_ppl["argmax"][:, 0] <= result.log_ppl[name][:, 0] + 1e-6).all()
    # a sampled token, at each position: never likelier than the argmax token given the same prefix
    sampled = teacher_forced_log_probs(net, context, result.tokens["sample"], cond)
    assert (result.log_ppl["sample"] >= -sampled.max(-1).values - 1e-6).all()


def test_top_k_tokens_are_within_the_k_most_likely(net: WorldModel, data, result: FramePerplexity) -> None:
    """ppl of every top-k token ≤ ppl of the k-th most likely token at that position (same prefix)."""
    context, _, cond = data
    log_p = teacher_forced_log_probs(net, context, result.tokens["top_k"], cond)
    kth = log_p.topk(K, dim=-1).values[..., -1]  # (b, n)
    # 1e-5: sampling read its logits through the KV cache, the check through one full forward
    assert (-result.log_ppl["top_k"] >= kth - 1e-5).all()


def test_long_context_is_cut_like_the_sliding_window(net: WorldModel, data, result: FramePerplexity) -> None:
    """Context beyond T - 1 frames (and its steps of the conditions) is dropped: same frames, same scores."""
    context, real, cond = data
    g = torch.Generator().manual_seed(4)
    longer = torch.cat([torch.randint(0, V, (B, 2, N), generator=g), context], dim=1)  # t0 = 4 > T - 1
    early = net.conditioner(B, 2, torch.randn(B, 2, M, E, generator=g), torch.randn(B, 2, 2, generator=g))
    cond = Conditions(torch.cat([early.text, cond.text], dim=1), torch.cat([early.actions, cond.actions], dim=1))
    got = frame_perplexity(net, longer, real, cond, k=K, generator=torch.Generator().manual_seed(2))
    for name in STRATEGIES:
        assert torch.equal(got.tokens[name], result.tokens[name])
        torch.testing.assert_close(got.log_ppl[name], result.log_ppl[name])


def test_default_conditions_are_null(net: WorldModel, data) -> None:
    context, real, _ = data
    got = frame_perplexity(net, context[:1], real[:1], k=K)
    want = token_log_perplexity(net, context[:1], real[:1], null_conditions(net, 1, T))
    torch.testing.assert_close(got.log_ppl["real"], want)


def test_summarize_and_mean_curves() -> None:
    ppl = torch.tensor([1.0, 1.2, 2.0, 10.0])
    stats = summarize(ppl.log())
    assert stats["frac_ppl_below_1_5"] == 0.5 and stats["max_ppl"] == pytest.approx(10.0)
    assert stats["ppl"] == pytest.approx(math.prod(ppl.tolist()) ** 0.25)  # exp(mean log-ppl): geometric mean
    assert stats["mean_log_ppl"] == pytest.approx(ppl.log().mean().item())
    curve = mean_curves({"real": torch.tensor([[1.0, 4.0], [9.0, 1.0]]).log()})["real"]
    torch.testing.assert_close(curve, torch.tensor([3.0, 2.0], dtype=torch.float64))


def test_plot_is_a_png(result: FramePerplexity, tmp_path) -> None:
    path = save_figure(token_perplexity_figure(mean_curves(result.log_ppl), k=K, title="test"), tmp_path / "fig6.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with Image.open(path) as img:
        img.verify()
    assert [p.name for p in tmp_path.iterdir()] == ["fig6.png"]  # no temp file left behind


def test_rerun_recording(result: FramePerplexity, tmp_path) -> None:
    curves = mean_curves(result.log_ppl)
    path = save_token_perplexity_rrd(tmp_path / "fig6.rrd", curves, k=K, summary=result.summary())
    assert path is not None and path.is_file() and [p.name for p in tmp_path.iterdir()] == ["fig6.rrd"]
    reader = RrdReader(str(path))
    assert len(reader.recordings()) == 1 and len(reader.blueprints()) == 1
    rows: dict[str, int] = {}
    for chunk in reader.stream().collect().stream().to_chunks():
        if not chunk.is_static:
            assert POSITION in chunk.timeline_names
            rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    assert rows == {f"/{root}/{name}": N for root in (ROOT, LOG_ROOT) for name in STRATEGIES}
