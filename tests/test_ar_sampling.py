"""GAIA-1 §5.1 sampling: guidance arithmetic (eq. 3), schedules (Fig. 7), KV-cached decoding, sliding window."""

from __future__ import annotations

import pytest
import torch

from gaia_app.diffusion.ar_sampling import AutoregressiveSampler, TokenPicker
from gaia_app.diffusion.guidance import ClassifierFreeGuidance, ConstantSchedule, CosineSchedule, LinearSchedule
from gaia_app.models.gaia1.world_model import WorldModel
from gaia_app.pipelines.gaia1_world_model import WorldModelRolloutPipeline

V, T, M, N, E = 16, 3, 2, 5, 8


@pytest.fixture(scope="module", params=[(False, False), (True, False), (True, True)],
                ids=["plain", "previous_frame_shortcut", "both_shortcuts"])
def net(request) -> WorldModel:
    torch.manual_seed(0)
    frame_shortcut, action_shortcut = request.param
    return WorldModel(V, dim=32, depth=2, heads=4, kv_heads=2, frames=T, text_tokens=M, image_tokens=N, text_dim=E,
                      previous_frame_shortcut=frame_shortcut, action_shortcut=action_shortcut).eval()


def test_eq3_guidance_arithmetic() -> None:
    cond, uncond = torch.randn(3, V), torch.randn(3, V)
    guide = ClassifierFreeGuidance(scale=2.0)
    torch.testing.assert_close(guide(cond, uncond, 0.0), cond)  # s = 0 (weight 1 + s = 1): the conditional logits
    torch.testing.assert_close(guide(cond, uncond, 2.0), 3.0 * cond - 2.0 * uncond)
    torch.testing.assert_close(guide(cond, cond, 7.0), cond)  # identical streams: no change


def test_schedules_shapes_and_endpoints() -> None:
    tokens = LinearSchedule(start=1.0, end=0.2)(576)
    assert tokens.shape == (576,) and tokens[0] == pytest.approx(1.0) and tokens[-1] == pytest.approx(0.2)
    assert (tokens.diff() < 0).all()
    frames = CosineSchedule(plateau=3, end=0.1)(12)
    assert frames.shape == (12,)
    torch.testing.assert_close(frames[:4], torch.ones(4))
    assert frames[-1] == pytest.approx(0.1) and (frames.diff() <= 1e-6).all()
    assert torch.equal(ConstantSchedule()(4), torch.ones(4))
    table = ClassifierFreeGuidance(4.0, LinearSchedule(1.0, 0.0), CosineSchedule(0, 0.0)).scales(12, 576)
    assert table.shape == (12, 576) and table[0, 0] == pytest.approx(4.0) and table[-1].abs().max() < 1e-6


def conds(net: WorldModel, b: int, steps: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    text, actions = torch.randn(b, steps, M, E, generator=g), torch.randn(b, steps, 2, generator=g)
    keep = {"text": False, "actions": False}
    return (net.conditioner(b, steps, text, actions, keep),
            net.conditioner(b, steps, text, actions, {"text": True, "actions": False}))


@pytest.mark.parametrize("guided", [False, True])
def test_kv_cache_sampling_equals_full_recompute(net: WorldModel, guided: bool) -> None:
    context = torch.randint(0, V, (2, 2, N), generator=torch.Generator().manual_seed(1))
    cond, uncond = conds(net, 2, 2 + 4)
    guidance = ClassifierFreeGuidance(2.0, LinearSchedule()) if guided else None
    kw = dict(uncond=uncond if guided else None, frames=4, guidance=guidance)  # 2 + 4 > T: crosses the window slide
    picker = TokenPicker("argmax")
    cached = AutoregressiveSampler(picker, use_cache=True)(net, context, cond, **kw)
    full = AutoregressiveSampler(picker, use_cache=False)(net, context, cond, **kw)
    assert torch.equal(cached, full)
    assert torch.equal(cached[:, :2], context)


def test_first_frame_argmax_matches_teacher_forced_logits(net: WorldModel) -> None:
    """Greedy decoding of one frame agrees with the net's own forward on the result (eq. 1 alignment)."""
    context = torch.randint(0, V, (1, 1, N), generator=torch.Generator().manual_seed(2))
    cond, _ = conds(net, 1, 2)
    out = AutoregressiveSampler(TokenPicker("argmax"))(net, context, cond, frames=1)
    assert torch.equal(net(out, cond)[:, 1].argmax(-1), out[:, 1])


def test_generation_from_no_context_matches_teacher_forcing(net: WorldModel) -> None:
    """t0 = 0 (text-only and unconditional rollouts): the first frame opens the window with no earlier step."""
    cond, _ = conds(net, 2, 2)
    out = AutoregressiveSampler(TokenPicker("argmax"))(net, torch.zeros(2, 0, N, dtype=torch.long), cond, frames=2)
    assert out.shape == (2, 2, N)
    assert torch.equal(net(out, cond).argmax(-1), out)


def test_sliding_window_generates_three_times_the_context(net: WorldModel) -> None:
    frames = 3 * T
    cond, _ = conds(net, 2, 1 + frames)
    context = torch.randint(0, V, (2, 1, N))
    out = AutoregressiveSampler(TokenPicker("top_k", k=4))(net, context, cond, frames=frames,
                                                           generator=torch.Generator().manual_seed(0))
    assert out.shape == (2, 1 + frames, N) and out.min() >= 0 and out.max() < V


def test_picker_modes() -> None:
    logits = torch.tensor([[0.0, 5.0, 4.0, -9.0]]).repeat(500, 1)
    g = torch.Generator().manual_seed(0)
    assert (TokenPicker("argmax")(logits) == 1).all()
    top2 = TokenPicker("top_k", k=2)(logits, g)
    assert set(top2.tolist()) == {1, 2}
    assert set(TokenPicker("sample", temperature=100.0)(logits, g).tolist()) == {0, 1, 2, 3}


def test_pipeline_futures_guidance_and_negative_prompt(net: WorldModel) -> None:
    context = torch.randint(0, V, (2, 1, N))
    text, negative = torch.randn(2, 3, M, E), torch.randn(2, 3, M, E)
    pipe = WorldModelRolloutPipeline(net, AutoregressiveSampler(TokenPicker("top_k", k=8)), ClassifierFreeGuidance(3.0))
    out = pipe(context, frames=2, text=text, num_futures=3, generator=torch.Generator().manual_seed(0))
    assert out.tokens.shape == (6, 3, N) and out.context_frames == 1
    assert torch.equal(out.tokens[:3, 0], context[:1].expand(3, -1, -1)[:, 0])
    negative_out = pipe(context, frames=2, text=text, negative_text=negative,
                        generator=torch.Generator().manual_seed(0))
    unconditional = WorldModelRolloutPipeline(net, AutoregressiveSampler(TokenPicker("argmax")))(context, frames=2)
    assert negative_out.tokens.shape == unconditional.tokens.shape == (2, 3, N)


def test_text_scale_guides_prompted_rollouts_and_scale_the_others(net: WorldModel) -> None:
    """guidance.text_scale: a rollout prompted with text samples exactly as with scale=text_scale; one steered by
    actions alone exactly as with `scale`."""
    context = torch.randint(0, V, (2, 1, N))
    text, actions = torch.randn(2, 3, M, E), torch.randn(2, 3, 2) * torch.tensor([8.0, 0.03]) + torch.tensor([10.0, 0])

    def tokens(guidance: ClassifierFreeGuidance, **streams) -> torch.Tensor:
        pipe = WorldModelRolloutPipeline(net, AutoregressiveSampler(TokenPicker("sample")), guidance)
        return pipe(context, frames=2, generator=torch.Generator().manual_seed(3), **streams).tokens

    split = ClassifierFreeGuidance(scale=0.5, text_scale=6.0)
    assert torch.equal(tokens(split, text=text), tokens(ClassifierFreeGuidance(6.0), text=text))
    assert torch.equal(tokens(split, actions=actions), tokens(ClassifierFreeGuidance(0.5), actions=actions))
    assert not torch.equal(tokens(split, text=text), tokens(ClassifierFreeGuidance(0.5), text=text))
    assert split.for_rollout(prompted=False) is split and split.for_rollout(prompted=True).scale == 6.0
    with pytest.raises(ValueError, match=r"guidance.text_scale=-1.0: expected a finite number ≥ 0"):
        ClassifierFreeGuidance(scale=1.0, text_scale=-1.0)


def test_nucleus_keeps_the_fewest_likely_tokens_that_reach_p() -> None:
    """top_p: probabilities (0.5, 0.3, 0.15, 0.05): p = 0.8 keeps tokens 0 and 1 (renormalised 5 : 3), p = 0.81
    adds token 2, a tiny p keeps the most likely token alone."""
    logits = torch.tensor([0.5, 0.3, 0.15, 0.05]).log().repeat(20000, 1)
    generator = torch.Generator().manual_seed(0)
    drawn = TokenPicker("top_p", p=0.8)(logits, generator)
    assert set(drawn.tolist()) == {0, 1}
    assert abs((drawn == 0).float().mean().item() - 0.5 / 0.8) < 0.02
    assert set(TokenPicker("top_p", p=0.81)(logits, generator).tolist()) == {0, 1, 2}
    assert set(TokenPicker("top_p", p=1e-6)(logits, generator).tolist()) == {0}
    with pytest.raises(ValueError, match="0 < p ≤ 1"):
        TokenPicker("top_p", p=0.0)


@pytest.fixture(scope="module")
def rope_net() -> WorldModel:
    torch.manual_seed(0)
    return WorldModel(V, dim=32, depth=2, heads=4, kv_heads=2, frames=T, text_tokens=M, image_tokens=N, text_dim=E,
                      temporal_encoding="rope").eval()


def test_rotary_time_makes_logits_independent_of_where_the_window_starts(rope_net: WorldModel) -> None:
    """The property the rolling cache rests on: a window embedded from step 0 or continued after dropped steps gives
    the same hidden states."""
    from gaia_app.nn.attention import KVCache

    tokens = torch.randint(0, V, (1, 3, N), generator=torch.Generator().manual_seed(3))
    cond, _ = conds(rope_net, 1, 3)
    x = rope_net.embed(tokens, cond)
    step = rope_net.step_len
    alone = rope_net.decode(x[:, step:])  # steps 1, 2 as a window of their own
    cache = KVCache()
    rope_net.decode(x[:, :step], cache)  # step 0, then forgotten
    cache.drop_front(step)
    continued = rope_net.decode(x[:, step:], cache)
    torch.testing.assert_close(continued, alone, atol=1e-5, rtol=1e-5)
    learned = WorldModel(V, dim=32, depth=2, heads=4, kv_heads=2, frames=T, text_tokens=M, image_tokens=N, text_dim=E)
    assert "temporal" in dict(learned.named_parameters()) and "temporal" not in dict(rope_net.named_parameters())
    with pytest.raises(ValueError, match="temporal_encoding"):
        WorldModel(V, dim=32, depth=2, heads=4, frames=T, text_tokens=M, image_tokens=N, text_dim=E,
                   temporal_encoding="alibi")


@pytest.mark.parametrize("guided", [False, True])
def test_rolling_cache_slides_without_re_prefill_and_equals_full_recompute(guided: bool) -> None:
    """One layer: a rolled cache holds exactly the keys a re-prefilled window would (with more layers the deeper
    keys keep a trace of the dropped steps, SamplingSession's docstring), so it equals full recompute."""
    torch.manual_seed(0)
    rope_net = WorldModel(V, dim=32, depth=1, heads=4, kv_heads=2, frames=T, text_tokens=M, image_tokens=N,
                          text_dim=E, temporal_encoding="rope").eval()
    context = torch.randint(0, V, (2, 2, N), generator=torch.Generator().manual_seed(1))
    cond, uncond = conds(rope_net, 2, 2 + 3 * T)
    guidance = ClassifierFreeGuidance(2.0, LinearSchedule()) if guided else None
    kw = dict(uncond=uncond if guided else None, frames=3 * T, guidance=guidance)  # slides 3·T − 1 times
    picker = TokenPicker("argmax")
    calls = []
    decode = rope_net.decode
    rope_net.decode = lambda x, cache=None: calls.append(x.shape[1]) or decode(x, cache)  # positions per forward
    try:
        cached = AutoregressiveSampler(picker, use_cache=True)(rope_net, context, cond, **kw)
    finally:
        del rope_net.decode
    full = AutoregressiveSampler(picker, use_cache=False)(rope_net, context, cond, **kw)
    assert torch.equal(cached, full)
    assert max(calls[1:]) <= M + 2 + 1  # after the first prefill no forward feeds more than one step's edge


@pytest.mark.parametrize("rope", [False, True])
def test_a_session_extended_step_by_step_equals_the_whole_rollout(net: WorldModel, rope_net: WorldModel,
                                                                   rope: bool) -> None:
    """A closed loop's view: conditions appended one step at a time, frames sampled one per call, past several
    window slides (re-prefill with learned time, a rolled cache with rotary time) → the tokens of one call."""
    model = rope_net if rope else net
    context = torch.randint(0, V, (2, 2, N), generator=torch.Generator().manual_seed(4))
    cond, uncond = conds(model, 2, 2 + 2 * T)
    guidance = ClassifierFreeGuidance(1.5, ConstantSchedule())
    sampler = AutoregressiveSampler(TokenPicker("top_k", k=4))
    whole = sampler(model, context, cond, uncond, 2 * T, guidance, torch.Generator().manual_seed(9))
    session = sampler.session(model, context, cond.steps(0, 2), uncond.steps(0, 2), guidance,
                              torch.Generator().manual_seed(9))
    frames = []
    for t in range(2, 2 + 2 * T):
        session.extend(cond.steps(t, t + 1), uncond.steps(t, t + 1))
        frames.append(session.next_frame())
    assert torch.equal(torch.stack(frames, 1), whole[:, 2:])
    assert session.known_steps == 2 + 2 * T and session.tokens.shape[1] == T  # only the window is kept
    with pytest.raises(ValueError, match="no conditions for step"):
        session.next_frame()
    with pytest.raises(ValueError, match="guided: extend needs uncond"):
        session.extend(cond.steps(0, 1))
