"""The fixed-shape decode step (gaia_app/diffusion/compiled_decode.py, issue 51): the same tokens as eager decoding.

Equality runs the step uncompiled (`decode_step="static"`: the fixed shapes, the static cache, the masked attention,
the in-graph token choice); `torch.compile` itself runs once, on one small guided rolling case, with the `aot_eager`
backend (Dynamo capture and AOTAutograd's functionalisation of the in-place cache writes, without inductor's C++
build, which takes ≈20 s on a busy CPU; benchmarks/bench_compiled_decode.py runs inductor). CUDA graphs need a GPU:
benchmarks/gpu_checks.py.
"""

from __future__ import annotations

import logging

import pytest
import torch

from gaia_app.diffusion import compiled_decode
from gaia_app.diffusion.ar_sampling import AutoregressiveSampler, TokenPicker
from gaia_app.diffusion.guidance import ClassifierFreeGuidance, LinearSchedule
from gaia_app.models.gaia1.world_model import WorldModel
from gaia_app.pipelines.gaia1_world_model import WorldModelRolloutPipeline
from gaia_app.pipelines.simulator_episodes import RowwisePicker

V, T, M, N, E = 16, 3, 2, 5, 8


def tiny(encoding: str = "learned", shortcuts: bool = False) -> WorldModel:
    torch.manual_seed(0)
    return WorldModel(V, dim=32, depth=2, heads=4, kv_heads=2, frames=T, text_tokens=M, image_tokens=N, text_dim=E,
                      temporal_encoding=encoding, previous_frame_shortcut=shortcuts, action_shortcut=shortcuts).eval()


@pytest.fixture(scope="module", params=[("learned", False), ("learned", True), ("rope", True)],
                ids=["learned", "learned_shortcuts", "rope_shortcuts"])
def net(request) -> WorldModel:
    return tiny(*request.param)


def streams(net: WorldModel, b: int, steps: int):
    g = torch.Generator().manual_seed(0)
    text, actions = torch.randn(b, steps, M, E, generator=g), torch.randn(b, steps, 2, generator=g)
    cond = net.conditioner(b, steps, text, actions, {"text": False, "actions": False})
    return cond, net.conditioner(b, steps, text, actions, {"text": True, "actions": False})


def rollout(net: WorldModel, decode_step: str, picker: TokenPicker, guided: bool, frames: int = 2 * T, b: int = 2,
            **kw) -> torch.Tensor:
    """2 context steps + `frames`: past T the window slides (rolls for rope, re-prefills for learned time)."""
    cond, uncond = streams(net, b, 2 + frames)
    context = torch.randint(0, V, (b, 2, N), generator=torch.Generator().manual_seed(1))
    guidance = ClassifierFreeGuidance(2.0, LinearSchedule()) if guided else None
    sampler = AutoregressiveSampler(picker, decode_step=decode_step)
    return sampler(net, context, cond, uncond if guided else None, frames, guidance,
                   torch.Generator().manual_seed(5), **kw)


@pytest.fixture(autouse=True)
def one_thread():
    """One intra-op thread: these nets are tiny, and two OpenMP threads on cores other jobs keep busy stall."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def step_calls(monkeypatch) -> list[int]:
    """Counts the fixed-shape step's calls, outside any compiled code (so a silent fallback to eager fails)."""
    calls: list[int] = []
    call = compiled_decode.FixedStep.__call__
    monkeypatch.setattr(compiled_decode.FixedStep, "__call__", lambda self, *a: calls.append(1) or call(self, *a))
    return calls


@pytest.mark.parametrize("picker", [TokenPicker("argmax"), TokenPicker("top_k", k=4), TokenPicker("top_p", p=0.8)],
                         ids=["argmax", "top_k", "top_p"])
@pytest.mark.parametrize("guided", [False, True], ids=["unguided", "cfg"])
def test_static_step_gives_the_eager_tokens_across_slides(net: WorldModel, picker: TokenPicker, guided: bool,
                                                          step_calls: list[int]) -> None:
    eager = rollout(net, "eager", picker, guided)
    assert not step_calls
    static = rollout(net, "static", picker, guided)
    assert torch.equal(static, eager)
    assert len(step_calls) == 2 * T * (N - 1)  # every token after a frame's first, through every slide


def test_futures_in_one_batch_share_noise_under_guidance(step_calls: list[int]) -> None:
    """3 futures of 2 contexts, CFG on the batch, shared Gumbel noise per context (picked inside the step)."""
    net = tiny("rope", shortcuts=True)
    context = torch.randint(0, V, (2, 2, N), generator=torch.Generator().manual_seed(2))
    text = torch.randn(2, 2 + 2 * T, M, E, generator=torch.Generator().manual_seed(3))

    def tokens(decode_step: str, groups: torch.Tensor | None) -> torch.Tensor:
        sampler = AutoregressiveSampler(TokenPicker("top_k", k=6), decode_step=decode_step)
        pipe = WorldModelRolloutPipeline(net, sampler, ClassifierFreeGuidance(3.0, LinearSchedule()))
        return pipe(context, 2 * T, text=text, num_futures=3, generator=torch.Generator().manual_seed(0),
                    noise_groups=groups).tokens

    groups = torch.tensor([0, 1])
    for shared in (None, groups):
        assert torch.equal(tokens("static", shared), tokens("eager", shared))
    assert step_calls


def test_rolling_session_extended_step_by_step(step_calls: list[int]) -> None:
    """The simulator's use: one session, conditions appended per step, a frame per call, 3·T frames of rolling
    window (the static cache shifts in place), one generator per row (the vector simulator's RowwisePicker)."""
    net = tiny("rope", shortcuts=True)
    cond, uncond = streams(net, 2, 2 + 3 * T)
    context = torch.randint(0, V, (2, 2, N), generator=torch.Generator().manual_seed(4))
    guidance = ClassifierFreeGuidance(1.5)

    def episode(decode_step: str, picker) -> torch.Tensor:
        generators = [torch.Generator().manual_seed(s) for s in (7, 8)]
        generator = generators if isinstance(picker, RowwisePicker) else generators[0]
        session = AutoregressiveSampler(picker, decode_step=decode_step).session(
            net, context, cond.steps(0, 2), uncond.steps(0, 2), guidance, generator)
        frames = []
        for t in range(2, 2 + 3 * T):
            session.extend(cond.steps(t, t + 1), uncond.steps(t, t + 1))
            frames.append(session.next_frame())
        assert session.dropped_steps == 3 * T + 2 - (T - 1) - 1
        return torch.stack(frames, 1)

    for picker in (TokenPicker("sample"), RowwisePicker(TokenPicker("top_k", k=5))):
        assert torch.equal(episode("static", picker), episode("eager", picker))
    assert len(step_calls) == 2 * 3 * T * (N - 1)


def test_compiled_step_gives_the_eager_tokens(monkeypatch, step_calls: list[int]) -> None:
    monkeypatch.setattr(compiled_decode, "compile_options", lambda device: {"backend": "aot_eager", "fullgraph": True})
    net = tiny("rope", shortcuts=True)
    picker = TokenPicker("top_k", k=4)
    sampler = AutoregressiveSampler(picker, decode_step="compiled")
    cond, uncond = streams(net, 2, 2 + 2 * T)
    context = torch.randint(0, V, (2, 2, N), generator=torch.Generator().manual_seed(1))
    guidance = ClassifierFreeGuidance(2.0, LinearSchedule())
    for _ in range(2):  # the second rollout reuses the first one's step and graph
        compiled = sampler(net, context, cond, uncond, 2 * T, guidance, torch.Generator().manual_seed(5))
        assert torch.equal(compiled, rollout(net, "eager", picker, guided=True))
    assert sampler.steps.failure is None and len(sampler.steps.steps) == 1 and len(step_calls) == 2 * 2 * T * (N - 1)


def test_a_cache_smaller_than_the_window_is_refused() -> None:
    net = tiny()
    needed = T * net.step_len + M
    cond, _ = streams(net, 1, 3)
    sampler = AutoregressiveSampler(TokenPicker("argmax"), decode_step="static", cache_capacity=needed - 1)
    with pytest.raises(ValueError, match=rf"cache_capacity={needed - 1} positions is too small for the window of "
                                         rf"{needed} positions"):
        sampler(net, torch.zeros(1, 1, N, dtype=torch.long), cond, frames=1)
    with pytest.raises(ValueError, match="decode_step='jit'"):
        AutoregressiveSampler(decode_step="jit")
    with pytest.raises(ValueError, match="needs use_cache=True"):
        AutoregressiveSampler(decode_step="compiled", use_cache=False)


@pytest.mark.parametrize("where", ["at_compile", "at_first_call"])
def test_a_failing_compile_falls_back_to_eager_with_one_warning(monkeypatch, caplog, where: str) -> None:
    def broken(*args, **kwargs):
        if where == "at_compile":
            raise RuntimeError("no working C++ compiler")

        def run(*inputs):
            raise RuntimeError("InductorError: no working C++ compiler\n(details)")
        return run

    monkeypatch.setattr(torch, "compile", broken)
    net = tiny("rope")
    picker = TokenPicker("argmax")
    cond, _ = streams(net, 2, 2 + 2 * T)
    context = torch.randint(0, V, (2, 2, N), generator=torch.Generator().manual_seed(1))
    sampler = AutoregressiveSampler(picker, decode_step="compiled")
    with caplog.at_level(logging.WARNING, logger=compiled_decode.__name__):
        first = sampler(net, context, cond, frames=2 * T)
        second = sampler(net, context, cond, frames=2 * T)
    eager = rollout(net, "eager", picker, guided=False)
    assert torch.equal(first, eager) and torch.equal(second, eager)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "\n" not in warnings[0]
    assert "no working C++ compiler" in warnings[0] and "decoding eagerly" in warnings[0]


def test_one_compiled_sampler_with_and_without_shared_noise(monkeypatch, step_calls: list[int]) -> None:
    """A warm compiled step runs without Dynamo's guards, so a session whose step takes other inputs (shared noise
    or none) must get its own step: the same sampler, independent draws first, then futures sharing their noise."""
    monkeypatch.setattr(compiled_decode, "compile_options", lambda device: {"backend": "aot_eager", "fullgraph": True})
    net = tiny("rope", shortcuts=True)
    context = torch.randint(0, V, (2, 2, N), generator=torch.Generator().manual_seed(2))
    text = torch.randn(2, 2 + T, M, E, generator=torch.Generator().manual_seed(3))
    compiled_sampler = AutoregressiveSampler(TokenPicker("top_k", k=6), decode_step="compiled")

    def tokens(sampler: AutoregressiveSampler, groups: torch.Tensor | None) -> torch.Tensor:
        pipe = WorldModelRolloutPipeline(net, sampler, ClassifierFreeGuidance(3.0, LinearSchedule()))
        return pipe(context, T, text=text, num_futures=3, generator=torch.Generator().manual_seed(0),
                    noise_groups=groups).tokens

    groups = torch.tensor([0, 1])
    for shared in (None, groups, None):
        eager = tokens(AutoregressiveSampler(TokenPicker("top_k", k=6)), shared)
        assert torch.equal(tokens(compiled_sampler, shared), eager)
    assert compiled_sampler.steps.failure is None and step_calls


@pytest.mark.parametrize("picker", [TokenPicker("top_k", k=7), TokenPicker("top_p", p=0.7), TokenPicker("sample")],
                         ids=["top_k", "top_p", "sample"])
def test_a_draw_made_beforehand_picks_what_the_multinomial_picks(picker: TokenPicker) -> None:
    """Every draw (`finish`, and the compiled step's noise drawn before its call, `draw` + `finish_drawn`) picks
    the token torch.multinomial picks under the same generator, so seeded rollouts keep the tokens they had when
    `finish` called torch.multinomial; this holds while PyTorch's one-sample multinomial is argmax(probs / Exp(1)
    noise), which this pins."""
    logits = torch.randn(200, 3, 40, generator=torch.Generator().manual_seed(0)) * 3
    seeds = [torch.Generator().manual_seed(11) for _ in range(3)]
    for row in logits:
        prepared = picker.prepare(row)
        probs, index = prepared
        choice = torch.multinomial(probs, 1, generator=seeds[0])
        multinomial = (choice if index is None else index.gather(-1, choice)).squeeze(-1)
        noise = picker.draw(picker.draw_shape(3, 40), seeds[1], row.device)
        assert torch.equal(picker.finish_drawn(prepared, noise), multinomial)
        assert torch.equal(picker.finish(prepared, seeds[2]), multinomial)
    assert TokenPicker("argmax").draw_shape(3, 40) is None


@pytest.mark.parametrize("tokens_per_call", [2, 3], ids=["divides", "with_tail"])
@pytest.mark.parametrize("picker", [TokenPicker("argmax"), TokenPicker("top_k", k=4), TokenPicker("top_p", p=0.8)],
                         ids=["argmax", "top_k", "top_p"])
@pytest.mark.parametrize("guided", [False, True], ids=["unguided", "cfg"])
def test_several_tokens_per_call_give_the_eager_tokens(net: WorldModel, picker: TokenPicker, guided: bool,
                                                       tokens_per_call: int, step_calls: list[int]) -> None:
    """N − 1 = 4 tokens per frame after the first: 2 calls of 2, or one call of 3 and the one-token tail."""
    eager = rollout(net, "eager", picker, guided)
    cond, uncond = streams(net, 2, 2 + 2 * T)
    context = torch.randint(0, V, (2, 2, N), generator=torch.Generator().manual_seed(1))
    guidance = ClassifierFreeGuidance(2.0, LinearSchedule()) if guided else None
    sampler = AutoregressiveSampler(picker, decode_step="static", tokens_per_call=tokens_per_call)
    blocked = sampler(net, context, cond, uncond if guided else None, 2 * T, guidance,
                      torch.Generator().manual_seed(5))
    assert torch.equal(blocked, eager)
    assert len(step_calls) == 2 * T * 2  # per frame: 2 + 2, or 3 + the tail's 1


def test_several_tokens_per_call_with_shared_noise_compiled(monkeypatch, step_calls: list[int]) -> None:
    """3 futures of 2 contexts sharing Gumbel noise per context, 3 tokens per compiled call (Dynamo + AOTAutograd)."""
    monkeypatch.setattr(compiled_decode, "compile_options", lambda device: {"backend": "aot_eager", "fullgraph": True})
    net = tiny("rope", shortcuts=True)
    context = torch.randint(0, V, (2, 2, N), generator=torch.Generator().manual_seed(2))
    text = torch.randn(2, 2 + T, M, E, generator=torch.Generator().manual_seed(3))

    def tokens(sampler: AutoregressiveSampler, groups: torch.Tensor | None) -> torch.Tensor:
        pipe = WorldModelRolloutPipeline(net, sampler, ClassifierFreeGuidance(3.0, LinearSchedule()))
        return pipe(context, T, text=text, num_futures=3, generator=torch.Generator().manual_seed(0),
                    noise_groups=groups).tokens

    compiled = AutoregressiveSampler(TokenPicker("top_k", k=6), decode_step="compiled", tokens_per_call=3)
    for shared in (torch.tensor([0, 1]), None):
        assert torch.equal(tokens(compiled, shared), tokens(AutoregressiveSampler(TokenPicker("top_k", k=6)), shared))
    assert compiled.steps.failure is None and len(step_calls) == 2 * T * 2


@pytest.mark.parametrize("bad", [0, -1, 1.5, True])
def test_tokens_per_call_must_be_a_positive_integer(bad) -> None:
    with pytest.raises(ValueError, match="tokens_per_call"):
        AutoregressiveSampler(decode_step="static", tokens_per_call=bad)
