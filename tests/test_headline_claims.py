"""The project's headline claims, pinned with the shipped weights at test cost (issue 52): a change that breaks one of
them fails the suite. Each test reruns a headline measurement on one fixed context, with fixed seeds, as `make demo`
and the benchmarks run it; the full-size numbers live in docs/results.md (linked from each test).

- GAIA-1: one held-out context steered four ways (brake / accelerate / left / right, the futures sharing their
  sampling noise): the shipped inverse-dynamics probe reads each future moving the way it was commanded.
- GAIA-2: the demo's car inserted 9 m ahead (`model.add_agents`) is read as an agent by the shipped agent probe
  inside its projected box, and not in the same box of the real scene; the same for the road-users weights
  (gaia_app/weights/gaia2_road_users), whose world model has no agent raster.
- GAIA-1 video decoder: the shipped decoder, at the demo's sampler setting, flickers less than frame-by-frame
  decoding by the tokenizer on a fixed held-out clip.

Tiers: the GAIA-1 steering pin runs in the quick tier (`make test`, what CI runs); the GAIA-2 insertion pins and the
decoder pin run in the slow tier (`make test-slow`, before a change lands): 170–240 s of test time together, which
CI's 25 minutes on a slow 2-core machine cannot hold (docs/benchmarks.md, "Three test tiers and CI's 25 minutes").
Quick tests reach the same product lines with cheaper runs (tests/test_shipped_gaia2_weights.py rolls out the demo's
inserted car, tests/test_agent_fidelity.py reads one, the decoder tests decode with the antithetic sampler).

The metrics and pipelines are the project's own (gaia_app.pipelines, gaia_app.eval, gaia_app.data); the settings
are conf/generate.yaml's with the Makefile's demo overrides, which are copied below (GAIA1_PROTOCOL, GAIA2_DEMO):
a change to those must be made here too. The few lines of set-up (the context clip, the commanded actions, the car's
box) follow the showcase and the benchmarks without importing them. Thresholds come from measurements recorded next
to each assertion.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

import gaia_app
from gaia_app.data.agent_regions import box_mask
from gaia_app.data.clip import AgentBoxes
from gaia_app.data.synthetic import SyntheticClipDataset
from gaia_app.eval.agent_iou import load_agent_probe, overlap_counts, predicted_agents
from gaia_app.eval.controllability import load_probes, probe_clips, probed_actions, realised_contrasts
from gaia_app.eval.metrics import psnr, temporal_flicker
from gaia_app.pipelines.gaia1 import Gaia1Pipeline
from gaia_app.pipelines.gaia1_inputs import future_actions, future_frames
from gaia_app.pipelines.gaia2 import Gaia2Pipeline
from gaia_app.pipelines.gaia2_edits import with_added_agents
from tests.conftest import compose_config

pytestmark = pytest.mark.usefixtures("one_thread")

WEIGHTS = Path(gaia_app.__file__).resolve().parent / "weights"
SOURCE_FPS = 25.0  # the synthetic world's own rate
# the Makefile's PROTOCOL (make demo, the controllability table, the shipped weights' MANIFEST)
GAIA1_PROTOCOL = ["context.frames=4", "seconds=1.25", "guidance.scale=1.5", "guidance.text_scale=3"]
# the Makefile's GAIA2_DEMO
GAIA2_DEMO = ["model.chunks=3", "num_futures=1", "model.guidance.scale=3",
              "model.add_agents=[{category: car, centre: [9, 0, 0.75], size: [4.5, 1.9, 1.5]}]"]
# benchmarks/gaia2_inserted_car.py's READ_SHARE: a car is read in a frame when the agent probe marks at least this
# share of its projected box (a real car fills ~60–80 % of its box)
READ_SHARE = 0.25


def shipped(name: str) -> Path:
    """gaia_app/weights/<name>; the test skips when it is missing (never in this repo)."""
    folder = WEIGHTS / name
    if not folder.is_dir():
        pytest.skip(f"shipped weights {folder} are missing")
    return folder


# ---- GAIA-1: commanded futures -------------------------------------------------------------------------------


def steered_futures(tmp_path: Path) -> dict[str, torch.Tensor]:
    """The demo's command panel (generate.py mode=showcase, `make demo`) scored like the controllability table:
    context clip `context.index` of the held-out world `context.seed`, its 4 frames encoded, then one future per
    `showcase.commands` from their shared sampling noise (seed `seed`), decoded frame by frame by the tokenizer (the
    frames the probes were checked on). Returns the probed horizon-mean (speed, curvature) per command (C, 2), the
    commanded ones (C, 2), and the realised / commanded differences (accelerate − brake speed, left − right
    curvature; eval.controllability.realised_contrasts), each (2,)."""
    folder = shipped("gaia1")
    cfg = compose_config("generate", ["mode=showcase", "weights=gaia1", *GAIA1_PROTOCOL, "token_sampler.progress=false",
                                      "extras.print_config=false"], tmp_path)
    pipeline = Gaia1Pipeline.from_weights(folder, video_decoder=False, sampler=instantiate(cfg.token_sampler),
                                          guidance=instantiate(cfg.guidance))
    dynamics, _, _ = load_probes(folder / "probes", pipeline.image_size, pipeline.rate)
    rate, (height, width) = pipeline.rate, pipeline.image_size
    t0, frames = int(cfg.context.frames), future_frames(cfg.seconds, rate)
    # the context clip as the showcase renders it: only the frames at the world model's rate
    world = SyntheticClipDataset(num_clips=cfg.context.index + 1, seed=cfg.context.seed, height=height, width=width,
                                 clip_len=math.ceil((t0 + frames - 1) / rate * SOURCE_FPS) + 1, render_rate=rate)
    clip = probe_clips([world[cfg.context.index]], rate, t0 + frames)
    commands = [tuple(command) for command in cfg.showcase.commands]
    past = clip.actions[0, :t0].numpy()
    commanded = torch.from_numpy(np.stack([
        np.concatenate([past, future_actions(speed, curvature, frames, rate, float(past[-1, 0]))])
        for speed, curvature in commands])).float()  # (C, t0 + f, 2)
    context = pipeline.encode(clip.frames[0, :t0])[None].repeat(len(commands), 1, 1, 1)
    tokens, _ = pipeline.sample_batch(context, frames, actions=commanded,
                                      generator=torch.Generator().manual_seed(int(cfg.seed)),
                                      noise_groups=torch.zeros(len(commands), dtype=torch.long))  # one shared noise
    # the steps into frames t0 + 1 .. t0 + f − 1, as the controllability table scores them (error_row)
    probed = probed_actions(dynamics, pipeline.tokenizer_frames(tokens), t0 + 1)  # (C, s, 2)
    wanted = commanded[:, t0:-1]
    realised, difference = realised_contrasts(probed[:, None], wanted[:, None])
    return {"commands": commands, "probed": probed.mean(dim=1), "commanded": wanted.mean(dim=1),
            "realised": realised[0], "commanded_difference": difference[0]}


def test_gaia1_steered_futures_move_the_way_they_were_commanded(tmp_path: Path) -> None:
    """GAIA-1 controllability (docs/results.md, "GAIA-1 controllability"; full table in gaia_app/weights/MANIFEST.md,
    "Controllability": over 32 contexts × 6 seeds the model realises 2.25 m/s of the 3.68 m/s commanded
    accelerate − brake difference, curvature contrast error 0.0132 of 0.0400 commanded). Here `make demo`'s one
    context (world 1000, clip 0; 4 context frames, 8 generated; guidance 1.5; seed 42), its four futures sharing their
    noise: the shipped probe reads a faster future under accelerate than under brake, a left turn under left and a
    right turn under right.

    Measured (2026-11-28, weights v6): speed brake 6.08, accelerate 8.77 m/s, realised difference 2.69 of 3.84
    commanded; curvature left +0.0178, right −0.0177 1/m, difference 0.0355 of 0.0400 commanded. Over 16 draws
    (contexts 0–3 × seeds 42, 1, 2, 3, this one included) the realised speed difference ranged 1.18–9.24 m/s and
    the curvature difference 0.024–0.065, with left > 0 > right in all 16 (smallest |curvature| 0.0085): the
    thresholds below (1.0 m/s, 0.015 1/m, ±0.005 1/m) hold on every draw tried, and a model that ignored its commands
    would give 0 for both differences (futures from one noise under the same conditions are one future)."""
    out = steered_futures(tmp_path)
    probed = dict(zip(out["commands"], out["probed"].tolist()))
    speed, curvature = out["realised"].tolist()
    assert out["commanded_difference"][0] > 3.0 and out["commanded_difference"][1] > 0.03  # the demo's commands
    assert probed[("accelerate", "straight")][0] > probed[("brake", "straight")][0]
    assert speed > 1.0, f"accelerate − brake probed speed {speed:.2f} m/s (measured 2.69)"
    assert probed[("keep", "left")][1] > 0.005 and probed[("keep", "right")][1] < -0.005, probed
    assert curvature > 0.015, f"left − right probed curvature {curvature:.4f} 1/m (measured 0.0355)"


# ---- GAIA-2: the inserted car --------------------------------------------------------------------------------


def track_boxes(agents: list[AgentBoxes], track_id: int, camera, height: int, width: int) -> torch.Tensor:
    """(t, H, W) bool: the box of track `track_id` projected into `camera` on each frame of `agents`."""
    masks = []
    for boxes in agents:
        keep = boxes.track_id == track_id
        one = AgentBoxes(boxes.centre[keep], boxes.size[keep], boxes.yaw[keep], boxes.category[keep],
                         boxes.track_id[keep])
        masks.append(box_mask(one, camera, height, width))
    return torch.from_numpy(np.stack(masks))


def inserted_car_reading(tmp_path: Path, weights: str = "gaia2") -> dict[str, np.ndarray]:
    """`make demo`'s GAIA-2 rollout (generate.py model=gaia2 mode=rollout weights=gaia2 data=synthetic_rig plus the
    Makefile's GAIA2_DEMO: scene 0 of the held-out world 1000, 2 context steps, 3 chunks, guidance ×3 on the agent
    boxes, the car of model.add_agents 9 m ahead; seed 42), read like benchmarks/gaia2_inserted_car.py: the shipped
    agent probe on the front camera's generated frames, its marked pixels inside the car's projected box per frame
    (eval.agent_iou.overlap_counts), for the rollout and for the real scene through the tokenizer (the same scene
    without the car). `weights`: the shipped folder rolled out. Returns per generated frame the marked share of the box,
    for "car" and "real" (t,)."""
    folder = shipped(weights)
    cfg = compose_config("generate", ["model=gaia2", "mode=rollout", f"weights={weights}", "data=synthetic_rig",
                                      *GAIA2_DEMO, "model.sampler.progress=false", "extras.print_config=false"],
                         tmp_path)
    g = cfg.model
    pipeline = Gaia2Pipeline.from_weights(folder, instantiate(g.sampler), instantiate(g.guidance), cfg.device,
                                          cfg.data.get("resize_mode", "crop"), cfg.fps)
    probe, _ = load_agent_probe(shipped("probes"))
    steps = g.context_steps + g.chunks * (g.steps - g.context_steps)
    first = g.context_steps * pipeline.temporal
    world = instantiate(cfg.data.source, num_clips=cfg.context.index + 1, seed=cfg.context.seed,
                        clip_len=steps * pipeline.temporal)
    clip = pipeline.encode(world[cfg.context.index])
    car = 1 + max((int(boxes.track_id.max()) for boxes in clip.agents or [] if len(boxes)), default=0)  # its track
    out = pipeline.rollout(with_added_agents(clip, OmegaConf.to_container(g.add_agents), first), g.context_steps,
                           g.steps, g.chunks, cfg.num_futures, seed=cfg.seed, drop=list(g.drop))
    front = {"car": pipeline.decode(out.latents)[0, 0, first:],
             "real": pipeline.decode(pipeline.window(out.clip, 0, steps)[0])[0, 0, first:]}
    boxes = track_boxes(out.clip.agents[first:], car, out.clip.cameras[0], *front["car"].shape[-2:])
    shares = {}
    for name, frames in front.items():
        agents = predicted_agents(probe, frames.float().cpu()[None])[0]
        counts = [overlap_counts(agents[i : i + 1], torch.ones_like(box[None]), box[None])
                  for i, box in enumerate(boxes)]
        shares[name] = np.array([marked / max(area, 1) for marked, area in counts])
    shares["area"] = boxes.flatten(1).sum(dim=1).numpy()
    return shares


@pytest.mark.slow
def test_gaia2_inserted_car_is_read_as_a_car_in_its_box(tmp_path: Path) -> None:
    """GAIA-2 agent insertion (docs/results.md, "GAIA-2 latent world model"; full table in docs/evaluation.md, "A car
    inserted into a GAIA-2 rollout": over 32 scenes of world 4960, a car 15 m ahead, the probe reads it in 0.92
    [0.88, 0.96] of the generated frames, target ≥ 0.70). Here `make demo`'s own scene and car (world 1000, scene 0,
    9 m ahead, 3 chunks = 24 generated frames, seed 42).

    Measured (2026-11-28, weights v3, agent probe v1): the probe marks ≥ 25 % of the car's box in 24 of 24 generated
    frames, 0.68 of the box's pixels over all frames (per frame 0.40–0.84); in the same boxes of the real scene
    (tokenized, no car inserted) 0.03 (per frame ≤ 0.08). The thresholds (read in ≥ 75 % of the frames, ≥ 0.40 of
    the box pooled, ≥ 0.3 more than the real scene) leave room for small model changes, while a rollout without the
    car fails each of them (the same scene and seed rolled out 2 chunks without the car: read in 1 of 16 frames,
    0.09 pooled; with it 15 of 16 and 0.46)."""
    shares = inserted_car_reading(tmp_path)
    assert (shares["area"] > 0).all()  # the car is in view on every generated frame
    read = float((shares["car"] >= READ_SHARE).mean())
    pooled = {name: float((shares[name] * shares["area"]).sum() / shares["area"].sum()) for name in ("car", "real")}
    assert read >= 0.75, f"car read in {read:.2f} of the generated frames (measured 1.00)"
    assert pooled["car"] >= 0.40, f"probed share of the car's box {pooled['car']:.2f} (measured 0.68)"
    assert pooled["car"] - pooled["real"] >= 0.3, pooled


@pytest.mark.slow
def test_gaia2_road_users_inserted_car_is_read_without_a_raster(tmp_path: Path) -> None:
    """The same reading of gaia_app/weights/gaia2_road_users (the s = 4 road-users tokenizer with a world model that
    reads its agents by a box-masked cross-attention only, no raster, trained with the agent-weighted loss;
    docs/paper_faithful.md, "The agent-weighted loss"): over 32 scenes of the unused world 5171 the probe reads the
    inserted car in 0.89 [0.86, 0.92] of the generated frames (target ≥ 0.70; the same arm without the weighted loss:
    0.62 on world 5121, where this one reads 0.85).

    Measured (2026-12-02): read in 24 of 24 generated frames, 0.61 of the box's pixels pooled (per frame 0.28–0.88);
    the real scene's same boxes 0.02. The thresholds are the shipped model's test's."""
    shares = inserted_car_reading(tmp_path, "gaia2_road_users")
    assert (shares["area"] > 0).all()
    read = float((shares["car"] >= READ_SHARE).mean())
    pooled = {name: float((shares[name] * shares["area"]).sum() / shares["area"].sum()) for name in ("car", "real")}
    assert read >= 0.75, f"car read in {read:.2f} of the generated frames (measured 1.00)"
    assert pooled["car"] >= 0.40, f"probed share of the car's box {pooled['car']:.2f} (measured 0.61)"
    assert pooled["car"] - pooled["real"] >= 0.3, pooled


# ---- GAIA-1 video decoder ------------------------------------------------------------------------------------


def decoder_against_framewise(tmp_path: Path, clips: int = 1, frames: int = 12,
                              seed: int = 0) -> dict[str, torch.Tensor]:
    """benchmarks/eval_video_decoder.py's comparison on `clips` clips of world 31337 (the evaluation world of
    docs/video_decoder.md; `frames` frames at 6.25 Hz, two decoder windows for 12): the ground-truth tokens decoded
    by the shipped video decoder at `make demo`'s setting (decoder_sampler=antithetic_mean decoder_steps=8, no eq. 4
    blend, 6.25 Hz) and frame by frame by the tokenizer. Returns flicker and PSNR (b,) of each."""
    folder = shipped("gaia1")
    cfg = compose_config("generate", ["mode=showcase", "weights=gaia1", "upsample=0",
                                      "decoder_sampler=antithetic_mean", "decoder_steps=8",
                                      "decoder_blend.probability=0", "extras.print_config=false"], tmp_path)
    pipeline = Gaia1Pipeline.from_weights(folder, decoder_sampler=cfg.decoder_sampler, decoder_steps=cfg.decoder_steps,
                                          upsample=cfg.upsample)
    pipeline.decoder.progress = False
    height, width = pipeline.image_size
    world = SyntheticClipDataset(num_clips=clips, seed=31337, height=height, width=width, cameras=["front"],
                                 clip_len=4 * (frames - 1) + 1, fps=SOURCE_FPS)
    truth = torch.stack([torch.from_numpy(world[i].frames[0]) for i in range(clips)]).float()[:, ::4] / 127.5 - 1
    with torch.no_grad():
        tokens = torch.stack([pipeline.encode(clip) for clip in truth])
        decoded = {"framewise": pipeline.tokenizer_frames(tokens),
                   "decoder": pipeline.decoder.decode(tokens, torch.Generator().manual_seed(seed)).cpu()}
    return {f"{name}_{metric}": value for name, video in decoded.items() for metric, value in (
        ("flicker", temporal_flicker(video, truth)),
        ("psnr", psnr(video.flatten(0, 1), truth.flatten(0, 1)).view(clips, -1).mean(dim=1)))}


@pytest.mark.slow
def test_gaia1_video_decoder_flickers_less_than_frame_by_frame_decoding(tmp_path: Path) -> None:
    """GAIA-1 video decoder (docs/results.md, "GAIA-1 video decoder"; full table in docs/video_decoder.md, "Diagnosis
    and the decoder that wins": over 16 clips of world 31337, 8 draws in 4 antithetic pairs flicker −0.0015 ± 0.0008
    against frame-by-frame decoding, PSNR −0.08 ± 0.09 dB; issue 21's target: flicker below frame by frame, PSNR within
    0.5 dB). Here clip 0 of that world, 12 frames, the demo's sampler (antithetic_mean, 8 draws), decoder seed 0.

    Measured (2026-11-28, decoder of weights v6): flicker 0.05401 against 0.05514 frame by frame (−0.00112, 2 %
    lower; with decoder seed 1: −0.00110, so the sampling noise moves it by ~2e-5, 50× less than the gap; clips 1–3:
    −0.0016, −0.0022, −0.0007). PSNR 25.61 against 25.88 dB (−0.27 dB, inside issue 21's 0.5 dB)."""
    out = decoder_against_framewise(tmp_path)
    flicker = float(out["decoder_flicker"][0] - out["framewise_flicker"][0])
    assert flicker < 0, f"decoder flicker − frame by frame {flicker:+.5f} (measured −0.00112)"
    psnr_gap = float(out["decoder_psnr"][0] - out["framewise_psnr"][0])
    assert psnr_gap > -0.5, f"decoder PSNR − frame by frame {psnr_gap:+.2f} dB (measured −0.27; issue 21's target)"
