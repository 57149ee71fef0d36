"""GAIA-2 inference modes and guidance on a small untrained (perturbed) latent world model."""

from __future__ import annotations

import pytest
import torch
from einops import rearrange

from gaia_app.diffusion.flow_matching import FlowSampler
from gaia_app.pipelines.gaia2_world_model import (
    Guidance,
    LatentWorldModelPipeline,
    agent_token_positions,
    with_window,
)
from tests.models.test_gaia2_latent_world_model import conditions, model

SHAPE = (1, 3, 3, 8, 8, 14)


def pipeline(guidance: Guidance | None = None, steps: int = 4) -> LatentWorldModelPipeline:
    return LatentWorldModelPipeline(model(), FlowSampler(steps=steps, schedule="uniform"), guidance)


def test_from_scratch_shapes_and_determinism() -> None:
    pipe = pipeline()
    a = pipe.from_scratch(SHAPE, conditions(), torch.Generator().manual_seed(0))
    b = pipe.from_scratch(SHAPE, conditions(), torch.Generator().manual_seed(0))
    assert a.shape == SHAPE and torch.equal(a, b)
    assert pipe.counter.calls == [3 * 3 * 112] * 8  # 4 solver steps × 2 runs; 3 latent steps × 3 cameras × 8×14


def test_rollout_keeps_the_context_and_takes_new_controls_per_chunk() -> None:
    pipe = pipeline()
    context = torch.randn(1, 3, 1, 8, 8, 14)
    chunks = [with_window(conditions(t=3, seed=s), slice(0, 3)) for s in (1, 2)]
    out = pipe.rollout(context, chunks, chunk_steps=2, generator=torch.Generator().manual_seed(0))
    assert out.shape == (1, 3, 5, 8, 8, 14)
    assert torch.equal(out[:, :, :1], context)
    same_controls = pipe.rollout(context, [chunks[0], chunks[0]], chunk_steps=2,
                                 generator=torch.Generator().manual_seed(0))
    assert torch.equal(out[:, :, :3], same_controls[:, :, :3])
    assert not torch.equal(out[:, :, 3:], same_controls[:, :, 3:])


def test_inpainting_keeps_everything_outside_the_mask() -> None:
    pipe = pipeline()
    real = torch.randn(SHAPE)
    mask = torch.zeros(1, 3, 3, 8, 14, dtype=torch.bool)
    mask[:, 0, :, 2:6, 4:10] = True
    out = pipe.inpaint(real, mask, conditions(), torch.Generator().manual_seed(0))
    keep = ~mask[:, :, :, None].expand_as(real)
    assert torch.equal(out[keep], real[keep]) and not torch.allclose(out[~keep], real[~keep])


def test_scene_editing_strength() -> None:
    pipe = pipeline(steps=10)
    real = torch.randn(SHAPE)
    unchanged = pipe.edit(real, conditions(), strength=0.0, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(unchanged, real)
    edited = pipe.edit(real, conditions(seed=3), strength=0.5, generator=torch.Generator().manual_seed(0))
    assert edited.shape == SHAPE and not torch.allclose(edited, real)
    assert len(pipe.counter.calls) == 5  # only the last half of the 10 steps runs


def test_spatially_selective_guidance_touches_only_agent_tokens_and_costs_less() -> None:
    cond = conditions()
    selected = agent_token_positions(cond, (8, 14), 1)
    assert 0 < selected.numel() < 3 * 112
    noise = torch.randn(SHAPE)
    x = {}
    counts = {}
    variants = {"none": Guidance(), "full": Guidance(scale=4.0), "spatial": Guidance(scale=4.0, spatial=True),
                "masked": Guidance(scale=4.0, spatial=True, spatial_pass="full"),
                "paired": Guidance(scale=4.0, spatial=True, spatial_pass="paired")}
    for name, guidance in variants.items():
        pipe = pipeline(guidance)
        x[name] = pipe.velocity(noise, torch.full((1, 3), 0.5), cond)
        counts[name] = pipe.counter.tokens
    outside = torch.ones(3 * 8 * 14, dtype=torch.bool)
    outside[selected] = False
    flat = {k: rearrange(v[0], "v t c h w -> t (v h w) c") for k, v in x.items()}
    assert torch.equal(flat["spatial"][:, outside], flat["none"][:, outside])
    assert not torch.allclose(flat["spatial"][:, ~outside], flat["none"][:, ~outside])
    assert counts["none"] < counts["spatial"] < counts["full"] == 2 * counts["none"]
    assert counts["spatial"] == counts["none"] + 3 * selected.numel()
    # the straightforward variant: plain CFG inside the agent regions, the conditional velocity outside them
    assert torch.equal(flat["masked"][:, outside], flat["none"][:, outside])
    torch.testing.assert_close(flat["masked"][:, ~outside], flat["full"][:, ~outside])
    assert counts["masked"] == counts["full"]
    # the report's saving changes the guided tokens: their unconditional pass lacks the rest of the scene
    assert not torch.allclose(flat["spatial"][:, ~outside], flat["masked"][:, ~outside])
    # the report's dual pass over the agent tokens alone: the direction comes from two passes that see the same tokens
    assert torch.equal(flat["paired"][:, outside], flat["none"][:, outside])
    assert counts["paired"] == counts["none"] + 2 * 3 * selected.numel()
    model, taus = pipeline(Guidance()).model, torch.full((1, 3), 0.5)
    direction = (model(noise, taus, cond, positions=selected)
                 - model(noise, taus, cond.without("agents"), positions=selected))
    expected = flat["none"][:, ~outside] + 3.0 * direction[0]  # (t, k, C) at patch 1; v_c + (s − 1)·direction
    torch.testing.assert_close(flat["paired"][:, ~outside], expected)
    assert not torch.allclose(flat["paired"][:, ~outside], flat["spatial"][:, ~outside])
    with pytest.raises(ValueError, match="spatial_pass"):
        Guidance(scale=2.0, spatial=True, spatial_pass="half")


def test_guidance_interval_guides_only_the_steps_whose_flow_time_lies_inside_it() -> None:
    cond, noise = conditions(), torch.randn(SHAPE)
    taus = torch.tensor([[0.2, 0.5, 1.0]])  # per latent step
    velocities, counts = {}, {}
    for name, guidance in {"none": Guidance(), "all": Guidance(scale=4.0, conditions=("action",)),
                           "early": Guidance(scale=4.0, conditions=("action",), interval=[0.0, 0.4]),
                           "never": Guidance(scale=4.0, conditions=("action",), interval=[0.6, 0.9])}.items():
        pipe = pipeline(guidance)
        velocities[name], counts[name] = pipe.velocity(noise, taus, cond), pipe.counter.tokens
    assert not torch.allclose(velocities["all"], velocities["none"])
    torch.testing.assert_close(velocities["early"][:, :, 0], velocities["all"][:, :, 0])  # τ 0.2: guided
    assert torch.equal(velocities["early"][:, :, 1:], velocities["none"][:, :, 1:])  # τ 0.5 and 1: conditional only
    # no step inside: the second pass is skipped altogether
    assert torch.equal(velocities["never"], velocities["none"])
    assert counts["never"] == counts["none"] == counts["all"] / 2
    for bad in ([0.5, 0.5], [-0.1, 0.5], [0.2]):
        with pytest.raises(ValueError, match=r"guidance.interval=.*expected \[lo, hi\] with 0 ≤ lo < hi ≤ 1"):
            Guidance(scale=2.0, interval=bad)
