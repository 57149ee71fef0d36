"""Gaia2Pipeline's library API (one call per mode, a typed output) with the shipped GAIA-2 weights: what a user who
never touches Hydra runs (docs/latent_world_model.md, "Inference modes")."""

from __future__ import annotations

import pytest
import torch

from gaia_app.data.clip import ClipError
from gaia_app.data.synthetic import SyntheticClipDataset
from gaia_app.diffusion.flow_matching import FlowSampler
from gaia_app.pipelines.gaia2 import Gaia2Output, Gaia2Pipeline
from gaia_app.pipelines.gaia2_edits import InpaintRegion, cut_steps, with_added_agents

pytestmark = pytest.mark.usefixtures("one_thread")

CAMERAS = ["front", "front_left", "front_right"]


@pytest.fixture(scope="module")
def pipeline() -> Gaia2Pipeline:
    return Gaia2Pipeline.from_weights("gaia2", sampler=FlowSampler(steps=2, progress=False))


@pytest.fixture(scope="module")
def clip(pipeline: Gaia2Pipeline):
    """A held-out 3-camera scene, encoded: 3 latent steps of 4 frames."""
    world = SyntheticClipDataset(num_clips=1, seed=1000, height=64, width=112, cameras=CAMERAS, clip_len=12, fps=12.5)
    return cut_steps(pipeline.encode(world[0]), 3)


def test_every_mode_returns_a_typed_output(pipeline: Gaia2Pipeline, clip) -> None:
    outputs = {"scratch": pipeline.scratch(clip, 2, num_futures=2, seed=1),
               "rollout": pipeline.rollout(clip, context_steps=1, steps=2, chunks=2, seed=1),
               "inpaint": pipeline.inpaint(clip, 2, InpaintRegion("box", (0.5, 0.5, 1.0, 1.0), ("front",)), seed=1),
               "edit": pipeline.edit(clip, 2, strength=0.5, seed=1)}
    for mode, out in outputs.items():
        assert isinstance(out, Gaia2Output), mode
        assert out.latents.shape[1:] == (3, out.clip.mean.shape[1], 16, 8, 14), mode
        assert torch.isfinite(out.latents).all() and out.seconds_per_sample > 0, mode
    assert outputs["scratch"].latents.shape[0] == 2 and outputs["rollout"].latents.shape[2] == 3
    assert outputs["rollout"].first_generated_frame == 4 and outputs["scratch"].first_generated_frame == 0
    frames = pipeline.decode_samples(outputs["edit"].latents)
    assert frames.shape == (1, 3, 8, 3, 64, 112) and frames.abs().max() <= 1


def test_a_seed_fixes_the_samples_and_inpainting_keeps_the_rest(pipeline: Gaia2Pipeline, clip) -> None:
    region = InpaintRegion("box", (0.5, 0.5, 1.0, 1.0), ("front",))
    first, again = (pipeline.inpaint(clip, 2, region, seed=7).latents for _ in range(2))
    assert torch.equal(first, again)
    real, _ = pipeline.window(clip, 0, 2)
    kept = ~region.mask(clip, pipeline.window(clip, 0, 2)[1], tuple(real.shape), pipeline.world.model.patch)
    changed = (first - real).abs().amax(dim=3)  # (1, v, t, h, w)
    assert changed[kept].max() < 1e-5 and changed[~kept].max() > 0.1


def test_added_agents_and_bad_calls_are_named(pipeline: Gaia2Pipeline, clip) -> None:
    car = {"category": "car", "centre": [9.0, 0.0, 0.75], "size": [4.5, 1.9, 1.5], "velocity": [-3.0, 0.0]}
    edited = with_added_agents(clip, [car], first_frame=4)
    assert len(edited.agents[4]) == len(clip.agents[4]) + 1 and len(edited.agents[3]) == len(clip.agents[3])
    with pytest.raises(ValueError, match="context_steps=2, steps=2"):
        pipeline.rollout(clip, context_steps=2, steps=2, chunks=1)
    with pytest.raises(ClipError, match="has 3 latent steps"):
        pipeline.rollout(clip, context_steps=1, steps=2, chunks=3)
    with pytest.raises(ValueError, match="edit_strength=1.5"):
        pipeline.edit(clip, 2, strength=1.5)
    with pytest.raises(ValueError, match=r"inpaint.cameras: \['rear'\]"):
        pipeline.inpaint(clip, 2, InpaintRegion("box", cameras=("rear",)))
    with pytest.raises(ValueError, match="inpaint.box"):
        InpaintRegion("box", (0.5, 0.5, 0.4, 1.0))
    with pytest.raises(ValueError, match="add_agents\\[0\\].size"):
        with_added_agents(clip, [{**car, "size": [4.5, -1, 1.5]}], 4)
