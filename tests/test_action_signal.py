"""The action-signal diagnosis of GAIA-1 world models (gaia_app/eval/action_signal.py, issue 50 item 2)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from gaia_app.data.token_cache import TokenSegment, write_segment
from gaia_app.eval.action_signal import Layout, action_signal, markdown
from gaia_app.models.gaia1.world_model import WorldModel
from gaia_app.nn.attention import CausalSelfAttention
from gaia_app.nn.rope import StepRotary
from gaia_app.protocols.action_signal_report import main, parse_models


def tiny_net(**kwargs) -> WorldModel:
    torch.manual_seed(0)
    options = dict(vocab_size=32, dim=32, depth=2, heads=4, kv_heads=2, frames=4, text_tokens=2, image_tokens=6,
                   action_tokens=2, text_dim=8) | kwargs
    return WorldModel(**options).eval()


def windows(net: WorldModel, count: int = 3, seed: int = 1) -> list[tuple[torch.Tensor, torch.Tensor]]:
    g = torch.Generator().manual_seed(seed)
    tokens = torch.randint(0, net.vocab_size, (count, net.frames, net.n), generator=g)
    actions = torch.stack([torch.rand(count, net.frames, generator=g) * 20,
                           (torch.rand(count, net.frames, generator=g) - 0.5) * 0.06], dim=-1)
    return [(tokens[:2], actions[:2]), (tokens[2:], actions[2:])]


def uniform_share(layout: Layout) -> float:
    """Mean over the predicting positions of steps 1..T−1 of visible action tokens ÷ visible positions."""
    actions = layout.kinds()["actions"]
    shares = [float(actions[: q + 1].sum()) / (q + 1)
              for step in range(1, layout.steps) for q in layout.predicting(step).tolist()]
    return sum(shares) / len(shares)


def test_layout_puts_each_kind_where_the_world_model_embeds_it():
    layout = Layout(m=2, n=3, l=2, steps=3)
    kinds = layout.kinds()
    assert [int(kinds[k].sum()) for k in ("text", "image", "actions")] == [6, 9, 6]
    # the last text token predicts z_{t,0}, image tokens 0..n−2 the rest
    assert layout.predicting(1).tolist() == [8, 9, 10]
    assert kinds["text"][8] and kinds["image"][9] and kinds["image"][10]
    assert layout.previous_actions(1).tolist() == [5, 6]
    assert kinds["actions"][5] and kinds["actions"][6]


@pytest.mark.parametrize("rotary", [False, True])
def test_attention_probs_and_value_writes_add_up_to_the_attention_output(rotary):
    torch.manual_seed(0)
    attn = CausalSelfAttention(dim=32, heads=4, kv_heads=2).eval()
    x = torch.randn(2, 10, 32)
    rot = StepRotary(8, 5)(0, 10, x.device) if rotary else None
    queries = torch.tensor([0, 3, 9])
    probs, writes = attn.attention_probs(x, queries, rot), attn.value_writes(x)
    assert probs.shape == (2, 4, 3, 10) and writes.shape == (2, 4, 10, 32)
    assert torch.allclose(probs.sum(-1), torch.ones(2, 4, 3))
    assert probs[:, :, 0, 1:].abs().max() == 0  # the first position sees only itself
    rebuilt = torch.einsum("bhkj,bhjd->bkd", probs, writes)
    assert torch.allclose(rebuilt, attn(x, rotary=rot)[:, queries], atol=1e-5)


def test_statistics_are_shaped_and_bounded():
    net = tiny_net(action_shortcut=True, action_deltas=True)
    results = action_signal(net, windows(net))
    assert results["windows"] == 3 and len(results["layers"]) == 2 and len(results["counterfactual"]) == 3
    layout = Layout(net.m, net.n, net.l, net.frames)
    for row in results["layers"]:
        assert len(row["mass_all"]) == 4 and all(0 <= v <= 1 for v in row["mass_all"])
        assert all(p <= a + 1e-9 for p, a in zip(row["mass_nearest"], row["mass_all"]))
        assert row["uniform_all"] == pytest.approx(uniform_share(layout))
        assert row["write"] > 0
    assert results["kl_nats"] > 0
    assert set(results["grad_relative"]) == {"action_weight", "action_bias", "delta_weight", "token_embedding"}
    assert all(v > 0 for v in results["grad_input"].values())
    text = markdown(results, "tiny")
    assert "| embedding |" in text and "| 1 |" in text


def test_only_the_action_shortcut_puts_the_actions_into_the_embedded_image_positions():
    """The counterfactual share at the embedding is exactly 0 on GAIA-1's own layout: actions reach the image tokens
    only through attention."""
    paper = action_signal(tiny_net(), windows(tiny_net()))
    shortcut = action_signal(tiny_net(action_shortcut=True), windows(tiny_net()))
    assert paper["counterfactual"][0] == 0
    assert shortcut["counterfactual"][0] > 0.01
    assert paper["counterfactual"][-1] > 0  # through attention the actions still change the last layer


def test_the_mass_follows_attention_that_is_steered_to_the_action_tokens():
    """A layer whose keys are large only at action positions (direction e0) and whose queries read every other
    position's direction e1 puts nearly all its attention on the action tokens: the statistic reads the attention."""
    net = tiny_net(depth=1)
    e0, e1 = torch.eye(32)[0], torch.eye(32)[1]
    with torch.no_grad():
        net.conditioner.action_weight.zero_()
        net.conditioner.action_bias.copy_(e0 * 30)
        net.spatial.add_(e1)
        attn = net.transformer.blocks[0].attn
        attn.to_q.weight.zero_()
        attn.to_q.weight[:, 1] = 5.0
        attn.to_kv.weight.zero_()
        attn.to_kv.weight[:16, 0] = 5.0  # the keys of both K/V heads; the values stay zero
    results = action_signal(net, windows(net))
    assert min(results["layers"][0]["mass_all"]) > 0.9
    assert results["layers"][0]["uniform_all"] < 0.2


def with_text(net: WorldModel, batches: list[tuple[torch.Tensor, torch.Tensor]], seed: int = 2
              ) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
    """The windows with random encoded captions (b, T, m, e) as a third element."""
    g = torch.Generator().manual_seed(seed)
    return [(tokens, actions, torch.randn(*tokens.shape[:2], net.m, net.conditioner.text_proj.in_features,
                                          generator=g)) for tokens, actions in batches]


def test_the_text_stream_is_read_like_the_actions():
    """--stream text: the caption tokens get the same statistics; they enter only through attention (no shortcut), and
    its gradients are the text projection's."""
    net = tiny_net(action_shortcut=True)
    results = action_signal(net, with_text(net, windows(net)), stream="text")
    assert results["stream"] == "text" and results["windows"] == 3
    layout = Layout(net.m, net.n, net.l, net.frames)
    text = layout.kinds()["text"]
    shares = [float(text[: q + 1].sum()) / (q + 1)
              for step in range(1, layout.steps) for q in layout.predicting(step).tolist()]
    for row in results["layers"]:
        assert row["uniform_all"] == pytest.approx(sum(shares) / len(shares))
        assert all(p <= a + 1e-9 for p, a in zip(row["mass_nearest"], row["mass_all"]))
    # at the embedding only the last text token of each step (it predicts z_{t,0}) is itself text; the action shortcut
    # adds only the null action to the image positions (their norms move a little), since the actions are held null
    plain = action_signal(tiny_net(), with_text(net, windows(net)), stream="text")
    assert 0 < results["counterfactual"][0] == pytest.approx(plain["counterfactual"][0], rel=0.01)
    assert results["counterfactual"][-1] > results["counterfactual"][0]
    assert results["kl_nats"] > 0
    assert set(results["grad_relative"]) == {"text_weight", "text_bias", "token_embedding"}
    assert "stream: text" in markdown(results, "tiny") and "this step's caption" in markdown(results, "tiny")


def test_the_nearest_text_is_the_caption_of_the_predicted_step():
    layout = Layout(m=2, n=3, l=2, steps=3)
    assert layout.nearest("text", 1).tolist() == [7, 8]  # step 1 starts at 7: its caption, then its image tokens
    assert layout.kinds()["text"][7] and layout.kinds()["text"][8]
    assert layout.nearest("actions", 1).tolist() == layout.previous_actions(1).tolist()


def test_the_mass_follows_attention_that_is_steered_to_the_text_tokens():
    """Keys large only where the text projection writes (direction e0): the text mass reads nearly all attention,
    the action mass none of it."""
    net = tiny_net(depth=1)
    e0, e1 = torch.eye(32)[0], torch.eye(32)[1]
    with torch.no_grad():
        net.conditioner.text_proj.weight.zero_()
        net.conditioner.text_proj.bias.copy_(e0 * 30)
        net.spatial.add_(e1)
        attn = net.transformer.blocks[0].attn
        attn.to_q.weight.zero_()
        attn.to_q.weight[:, 1] = 5.0
        attn.to_kv.weight.zero_()
        attn.to_kv.weight[:16, 0] = 5.0
    batches = with_text(net, windows(net))
    text = action_signal(net, batches, stream="text")
    actions = action_signal(net, batches, stream="actions")
    assert min(text["layers"][0]["mass_all"]) > 0.9
    assert max(actions["layers"][0]["mass_all"]) < 0.05


def test_the_text_stream_needs_captions():
    net = tiny_net()
    with pytest.raises(ValueError, match="needs encoded captions"):
        action_signal(net, windows(net), stream="text")
    with pytest.raises(ValueError, match="stream 'speech'"):
        action_signal(net, windows(net), stream="speech")


def test_windows_that_do_not_fit_the_model_are_refused():
    net = tiny_net()
    tokens, actions = windows(net)[0]
    with pytest.raises(ValueError, match="tokens"):
        action_signal(net, [(tokens[:, :, :5], actions)])
    with pytest.raises(ValueError, match="no windows"):
        action_signal(net, [])


def test_report_on_the_shipped_weights_and_a_token_cache(tmp_path):
    """The protocol end to end: the shipped world model (112 tokens per frame, T = 12) on two held-out windows."""
    from gaia_app.weights.folders import shipped_folder

    rng = np.random.default_rng(0)
    for i in range(2):
        actions = np.stack([rng.uniform(4, 16, 12), rng.uniform(-0.02, 0.02, 12)], -1).astype(np.float32)
        write_segment(tmp_path / "tokens" / "val", TokenSegment(f"clip{i}", rng.integers(0, 1024, (12, 8, 14)),
                                                                actions))
    results = main(["--model", f"shipped={shipped_folder('gaia1')}", "--tokens", str(tmp_path / "tokens"),
                    "--out", str(tmp_path / "out"), "--windows", "2"])
    assert results["shipped"]["windows"] == 2
    saved = json.loads((tmp_path / "out" / "action_signal.json").read_text())
    # the shipped model has the action shortcut: its actions are in the embedded image positions already
    assert saved["shipped"]["counterfactual"][0] > 0
    # docs/paper_faithful.md: after its long training one layer-0 head of the shipped model reads the action tokens
    # (0.23 of its attention on held-out windows, 0.21 on these random ones, against a uniform share of 0.015)
    layer0 = saved["shipped"]["layers"][0]
    assert max(layer0["mass_all"]) > 5 * layer0["uniform_all"] and max(layer0["mass_nearest"]) > 0.05
    assert "**shipped**" in (tmp_path / "out" / "action_signal.md").read_text()


def test_text_report_on_the_shipped_weights_and_a_captioned_cache(tmp_path):
    """--stream text end to end: the shipped model's own (learned keyword) text encoder reads the cache's captions."""
    from gaia_app.weights.folders import shipped_folder

    rng = np.random.default_rng(0)
    captions = ["driving at night. snow is falling."] * 12
    actions = np.stack([rng.uniform(4, 16, 12), rng.uniform(-0.02, 0.02, 12)], -1).astype(np.float32)
    write_segment(tmp_path / "tokens" / "val", TokenSegment("clip", rng.integers(0, 1024, (12, 8, 14)), actions,
                                                            text=captions))
    results = main(["--model", f"shipped={shipped_folder('gaia1')}", "--tokens", str(tmp_path / "tokens"),
                    "--out", str(tmp_path / "out"), "--windows", "1", "--stream", "text"])
    assert results["shipped"]["stream"] == "text"
    assert results["shipped"]["kl_nats"] > 0  # the prompt changes the shipped model's predictions
    assert (tmp_path / "out" / "text_signal.json").exists() and (tmp_path / "out" / "text_signal.md").exists()
    write_segment(tmp_path / "bare" / "val", TokenSegment("clip", rng.integers(0, 1024, (12, 8, 14)), actions))
    with pytest.raises(ValueError, match="no captions"):
        main(["--model", f"shipped={shipped_folder('gaia1')}", "--tokens", str(tmp_path / "bare"),
              "--out", str(tmp_path / "out"), "--windows", "1", "--stream", "text"])


def test_model_arguments_are_checked(tmp_path):
    with pytest.raises(ValueError, match="NAME=PATH"):
        parse_models(["nothing"])
    with pytest.raises(FileNotFoundError, match="missing"):
        parse_models([f"missing={tmp_path / 'nope'}"])
    with pytest.raises(ValueError, match="twice"):
        parse_models([f"a={tmp_path}", f"a={tmp_path}"])
