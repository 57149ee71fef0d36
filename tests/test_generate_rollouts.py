"""generate.py GAIA-1 rollouts end to end on tiny checkpoints made here: every mode, 2 futures, 1 s.

The chain is the real one (GAIA-1 Fig. 1): tokenizer → token cache → world model → video decoder → rollouts;
each component trains for a step or two, so the futures are noise, but every file, frame count and
recording entry is what a trained run writes.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from rerun.chunk import RrdReader

from gaia_app.data.clip import ClipError
from gaia_app.data.synthetic import SyntheticClipDataset
from gaia_app.data.synthetic.export import export
from gaia_app.data.video_io import video_info
from gaia_app.tasks.generate import generate
from gaia_app.tasks.rollout import staging
from gaia_app.viz.gallery import make_gallery
from gaia_app.viz.screenshot import ViewerUnavailable, screenshot_recording
from tests.conftest import compose_config
from tests.tiny_checkpoints import GAIA1_SIZE

SIZE = GAIA1_SIZE  # 32×48: 96 tokens per frame, as the chain was trained (tests/tiny_checkpoints.py)
# 1 s at 6.25 Hz = 7 generated frames after 2 context frames: 9 frames → 4·9 − 3 = 33 at 25 Hz
FUTURE, CONTEXT, VIDEO_FRAMES = 7, 2, 33


@pytest.fixture(scope="module")
def checkpoints(gaia1_tiny: dict[str, Path]) -> dict[str, Path]:
    """The tiny GAIA-1 chain of tests/tiny_checkpoints.py, trained once for the whole run."""
    return gaia1_tiny


def run(checkpoints: dict[str, Path], run_dir: Path, *overrides: str, decoder: bool = True) -> dict:
    ckpts = [f"{k}={v}" for k, v in checkpoints.items() if decoder or k != "decoder_ckpt"]
    cfg = compose_config("generate", [*ckpts, "decoder_steps=1", "num_futures=2", "seconds=1.0",
                                      "extras.print_config=false", *SIZE, *overrides], run_dir)
    return generate(cfg)["results"]


MODES = {
    "video": [],
    "action": ["speed=accelerate", "curvature=left"],
    "text": ["prompt='It is night. It is raining.'"],
    "text_action": ["prompt='It is day.'", "speed=[5,5,6,6,7,7,8]", "curvature=0.01"],
    "text_only": ["prompt='It is snowing.'"],
    "unconditional": [],
}


# the modes whose futures go through the video decoder (25 Hz); the others are rendered by the tokenizer at the world
# model's 6.25 Hz: the conditioning differs by mode, the decoding does not (and costs most of a run)
DECODED = {"action", "video"}


@pytest.mark.parametrize("mode", sorted(MODES))
def test_every_mode_writes_futures_grid_tokens_and_recording(checkpoints, tmp_path: Path, mode: str) -> None:
    decoded = mode in DECODED
    results = run(checkpoints, tmp_path, f"mode={mode}", *MODES[mode], decoder=decoded)
    context = 0 if mode in ("text_only", "unconditional") else CONTEXT
    steps = context + FUTURE
    frames = 4 * steps - 3 if decoded else steps
    assert results["generated_frames"] == FUTURE and results["context_frames"] == context
    assert results["video_frames"] == frames and results["fps"] == (25.0 if decoded else 6.25)
    for k in range(2):
        info = video_info(tmp_path / f"future_{k}.mp4")
        assert info.num_frames == frames and (info.height, info.width) == (32, 48)
    grid = video_info(tmp_path / "grid.mp4")
    assert grid.num_frames == frames and grid.width > 3 * 48  # real clip + 2 futures side by side
    tokens = np.load(tmp_path / "tokens.npy")
    assert tokens.shape == (2, steps, 8, 12) and tokens.min() >= 0 and tokens.max() < 512
    conditioning = json.loads((tmp_path / "conditioning.json").read_text())
    assert conditioning["mode"] == mode
    assert not list(tmp_path.glob(".rollout-*"))
    assert_recording(tmp_path / "rollout.rrd", mode, steps, context, frames)


def assert_recording(path: Path, mode: str, steps: int, context: int, frames: int) -> None:
    """The recording holds the real clip (with context), both futures' video (`frames` frames) and tokens,
    perplexity, and the actions or prompts the mode used, on the `frame` timeline."""
    rows: dict[str, int] = {}
    for chunk in RrdReader(str(path)).stream().collect().stream().to_chunks():
        if not chunk.is_static:
            rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    expected = {"/future_0/video", "/future_1/video", "/future_0/tokens", "/future_1/perplexity", "/phase"}
    expected |= {"/real"} if context else set()
    expected |= {"/actions/speed", "/actions/curvature"} if "action" in mode else set()
    expected |= {"/prompt"} if "text" in mode else set()
    assert expected <= set(rows), expected - set(rows)
    assert rows["/future_1/video"] == frames and rows["/future_0/tokens"] == steps
    assert rows["/future_0/perplexity"] == steps - context and rows.get("/real", frames) == frames


def test_action_presets_and_explicit_values_reach_the_conditioning(checkpoints, tmp_path: Path) -> None:
    run(checkpoints, tmp_path / "brake", "mode=action", "speed=brake", "curvature=strong_right", decoder=False)
    brake = json.loads((tmp_path / "brake" / "conditioning.json").read_text())
    commanded = np.array(brake["commanded_actions"])
    assert (commanded.shape == (FUTURE, 2) and np.all(np.diff(commanded[:, 0]) <= 0)
            and np.allclose(commanded[:, 1], -0.05))
    assert len(brake["actions"]) == CONTEXT + FUTURE
    speeds = "[1,2,3,4,5,6,7]"
    run(checkpoints, tmp_path / "list", "mode=action", f"speed={speeds}", decoder=False)
    listed = json.loads((tmp_path / "list" / "conditioning.json").read_text())
    assert [row[0] for row in listed["commanded_actions"]] == [1, 2, 3, 4, 5, 6, 7]


def test_without_a_decoder_frames_come_at_the_world_model_rate(checkpoints, tmp_path: Path) -> None:
    results = run(checkpoints, tmp_path, "mode=video", decoder=False)
    assert results["fps"] == 6.25 and results["video_frames"] == CONTEXT + FUTURE
    assert video_info(tmp_path / "future_0.mp4").num_frames == CONTEXT + FUTURE


def test_guidance_schedule_and_negative_prompt_are_recorded(checkpoints, tmp_path: Path) -> None:
    results = run(checkpoints, tmp_path, "mode=text", "prompt='It is night.'", "negative_prompt='It is day.'",
                  "guidance=scheduled", "guidance.scale=2.0", "num_futures=3", decoder=False)
    assert np.load(tmp_path / "tokens.npy").shape[0] == 3 and results["futures"] == 3
    scales = json.loads((tmp_path / "conditioning.json").read_text())["guidance"]["per_frame_mean_scale"]
    assert len(scales) == FUTURE and scales[0] == pytest.approx(1.0) and scales[-1] == pytest.approx(0.0)
    assert scales == sorted(scales, reverse=True)


def test_long_rollouts_slide_past_the_context_window(checkpoints, tmp_path: Path) -> None:
    # the tiny world model's window is 4 steps; 2 s = 13 generated frames slide it 11 times
    results = run(checkpoints, tmp_path, "mode=video", "seconds=2.0", "num_futures=1", decoder=False)
    assert results["generated_frames"] == 13
    assert np.load(tmp_path / "tokens.npy").shape == (1, CONTEXT + 13, 8, 12)


@pytest.mark.parametrize(("overrides", "error", "match"), [
    (["mode=action"], ValueError, "needs speed= and/or curvature="),
    (["mode=action", "speed=[1,2]"], ValueError, "2 values for 7 future steps"),
    (["mode=action", "curvature=hard_left"], ValueError, "curvature='hard_left': expected one of"),
    (["mode=text"], ValueError, "needs a prompt"),
    (["mode=video", "prompt=hello"], ValueError, "takes no prompt"),
    (["mode=text", "prompt=x", "negative_prompt=y"], ValueError, "set guidance.scale > 0"),
])
def test_bad_input_fails_clearly_and_leaves_no_outputs(checkpoints, tmp_path: Path, overrides, error, match) -> None:
    with pytest.raises(error, match=match):
        run(checkpoints, tmp_path, *overrides, decoder=False)
    assert_no_outputs(tmp_path)


def assert_no_outputs(run_dir: Path) -> None:
    """Only the run's config and log: no video, token, recording or staging file."""
    assert not [p.name for p in run_dir.iterdir() if p.name not in (".hydra", "config_resolved.yaml", "generate.log")]


def test_a_context_clip_shorter_than_needed_is_named(checkpoints, tmp_path: Path) -> None:
    # 8 frames at 25 Hz = 0.28 s: 2 frames at 6.25 Hz, one short of the 3 context frames asked for
    export(tmp_path / "clips", SyntheticClipDataset(num_clips=1, seed=3, height=32, width=48, clip_len=8),
           progress=False)
    with pytest.raises(ClipError,
                       match=r"context clip 'synthetic-s3-000000' has 2 frames at 6.25 Hz .* needs 3 context"):
        run(checkpoints, tmp_path / "run", "mode=video", "context.source=folder",
            f"context.folder={tmp_path / 'clips'}", "context.frames=3", decoder=False)
    assert_no_outputs(tmp_path / "run")


def test_a_checkpoint_of_the_wrong_component_is_named(checkpoints, tmp_path: Path) -> None:
    wrong = {**checkpoints, "world_model_ckpt": checkpoints["decoder_ckpt"]}
    with pytest.raises(TypeError,
                       match=r"world_model_ckpt=.*holds a video_decoder \(VideoDecoderModule\) checkpoint, "
                             "expected a world_model checkpoint"):
        run(wrong, tmp_path, "mode=video")


def test_controllability_mode_scores_model_ceiling_and_floor(checkpoints, tmp_path: Path) -> None:
    args = ["mode=controllability", "seconds=0.5", "controllability.probe_clips=4", "controllability.probe_steps=3",
            "controllability.contexts=2", "controllability.commands=[[brake,left],[keep,right]]",
            "controllability.prompts.time_of_day=[night]", "~controllability.prompts.weather",
            "controllability.text_repeats=2", "controllability.floor_repeats=3", "controllability.real_clips=6"]
    results = run(checkpoints, tmp_path / "first", *args, decoder=False)
    rows = results["actions"]["rows"]
    assert set(rows) == {"ceiling", "tokenized", "model", "floor", "reference"}
    assert rows["tokenized"] != rows["ceiling"]  # the real frames went through the (lossy) tokenizer
    for row in rows.values():
        assert row["speed_mae"]["n"] == 2
        assert row["speed_mae"]["low"] <= row["speed_mae"]["mean"] <= row["speed_mae"]["high"]
        assert np.isfinite(row["curvature_mae"]["mean"]) and np.shape(row["per_command"]) == (2, 2)
        assert row["speed_contrast"]["n"] == 2 and np.isfinite(row["curvature_contrast"]["mean"])
        # the signed diagnostic: |realised − commanded| averaged over contexts is the contrast error
        realised = row["realised"]["speed_contrast"]
        assert realised["n"] == 2 and realised["sd"] >= 0 and np.isfinite(realised["commanded"])
        assert np.mean(realised["per_context"]) == pytest.approx(realised["mean"])
    assert set(results["actions"]["checks"]) == {"speed_contrast", "curvature_contrast"}
    assert results["actions"]["contrasts"] == {"speed_contrast": ["keep/right", "brake/left"],
                                               "curvature_contrast": ["brake/left", "keep/right"]}
    text = results["text"]
    assert text["targets"] == ["time_of_day=night"] and set(text["rows"]) == {"ceiling", "tokenized", "model", "floor"}
    model = text["rows"]["model"]["time_of_day=night"]
    assert model["n"] == 2 and 0 <= model["low"] <= model["mean"] <= model["high"] <= 1
    assert text["rows"]["floor"]["time_of_day=night"]["n"] == 3 == text["floor_rollouts"]  # batches of 2, then 1
    table = (tmp_path / "first" / "controllability.md").read_text()
    assert "| model (action-conditioned) |" in table and "| chance | 0.33 |" in table and "probe check" in table
    assert "| realised difference (diagnostic) | speed (m/s), commanded" in table
    discrimination = results["actions"]["discrimination"]
    assert set(discrimination) == {"speed_contrast", "curvature_contrast"}
    assert discrimination["speed_contrast"]["n"] == 2 and discrimination["speed_contrast"]["own_nats"] > 0
    assert "Command discrimination (diagnostic" in table
    # fidelity against the real continuations under the same commands (issue 49 item 4)
    fidelity = results["actions"]["fidelity"]
    assert fidelity["metrics"] == ["psnr", "ssim", "fvmd"] and set(fidelity["rows"]) == {"tokenized", "model",
                                                                                          "floor", "held"}
    assert all(np.isfinite(v) for row in fidelity["rows"].values() for v in row.values())
    assert fidelity["rows"]["tokenized"] != fidelity["rows"]["model"] != fidelity["rows"]["held"]
    assert "| held last context frame |" in table and "fvmd ↓" in table
    assert json.loads((tmp_path / "first" / "controllability.json").read_text())["actions"]["contexts"] == 2
    # the probes are saved and reused: a second run with them trains nothing and scores the real rows identically
    probes = tmp_path / "first" / "probes"
    assert (probes / "probes.safetensors").is_file() and (probes / "probes.yaml").is_file()
    again = run(checkpoints, tmp_path / "second", *args, f"controllability.probes={probes}", decoder=False)
    assert again["actions"]["rows"]["reference"] == rows["reference"]
    assert again["actions"]["rows"]["ceiling"] == rows["ceiling"]
    assert again["actions"]["rows"]["tokenized"] == rows["tokenized"]  # the tokenizer round trip is deterministic
    assert again["actions"]["fidelity"]["rows"]["held"] == fidelity["rows"]["held"]
    with pytest.raises(ValueError, match="controllability.fidelity.metrics has agent_iou"):
        run(checkpoints, tmp_path / "third", *args, "controllability.fidelity.metrics=[psnr,agent_iou]", decoder=False)
    with pytest.raises(ValueError, match="set controllability.fidelity.lpips_checkpoint"):
        run(checkpoints, tmp_path / "fourth", *args, "controllability.fidelity.metrics=[lpips]", decoder=False)


def test_command_discrimination_scores_real_futures_teacher_forced(checkpoints, tmp_path: Path) -> None:
    """Within one window the per-frame nats come from one forward and equal the frame-by-frame teacher forcing of
    token_log_perplexity; a command contrasted with itself discriminates nothing, and another one changes the score."""
    from gaia_app.eval.token_perplexity import token_log_perplexity
    from gaia_app.protocols.controllability import command_discrimination, future_nats
    from gaia_app.protocols.loading import load_pipeline

    cfg = compose_config("generate", [f"{k}={v}" for k, v in checkpoints.items() if k != "decoder_ckpt"] + [
        "extras.print_config=false", *SIZE], tmp_path)
    pipeline = load_pipeline(cfg, video_decoder=False)
    h, w = pipeline.token_grid
    t = pipeline.world_model.frames  # one window: the per-frame path sees the same context
    g = torch.Generator().manual_seed(0)
    tokens = torch.randint(0, pipeline.world_model.vocab_size, (2, 2, t, h, w), generator=g)  # (C, N, t, h, w)
    actions = torch.stack([torch.full((2, t, 2), 3.0), torch.full((2, t, 2), 12.0)])
    actions[..., 1] = torch.tensor([0.03, -0.03])[:, None, None]
    nats = future_nats(pipeline, tokens[0], actions[0], t0=2)
    cond = pipeline.rollouts.conditions(2, t, None, actions[0])
    flat = tokens[0].flatten(2)
    with torch.no_grad():
        per_frame = torch.stack([token_log_perplexity(pipeline.world_model, flat[:, :i], flat[:, i],
                                                      cond.steps(0, i + 1)).mean(-1)
                                 for i in range(2, t)], dim=1)
    torch.testing.assert_close(nats, per_frame.mean(dim=1), rtol=1e-4, atol=1e-4)
    same = command_discrimination(pipeline, tokens, actions, 2, [(0, 0), (1, 1)])
    assert same["speed_contrast"]["mean"] == 0 and same["curvature_contrast"]["mean"] == 0
    other = command_discrimination(pipeline, tokens, actions, 2, [(1, 0), (0, 1)])
    assert abs(other["speed_contrast"]["mean"]) > 0 and other["speed_contrast"]["n"] == 2


def test_gallery_strips_and_headless_viewer_screenshot(checkpoints, tmp_path: Path) -> None:
    demo = tmp_path / "demo"
    run(checkpoints, demo / "rollout_action", "mode=action", "speed=accelerate", "curvature=left")
    run(checkpoints, demo / "rollout_text", "mode=text", "prompt='It is night.'", decoder=False)
    written = make_gallery(demo, tmp_path / "gallery")
    strip = cv2.imread(str(tmp_path / "gallery" / "rollout_action.png"))
    assert strip.shape[0] == 3 * 2 * 32 and strip.shape[1] > 2 * 3 * 48  # 3 rows at 2×, real + 2 futures wide
    assert cv2.imread(str(tmp_path / "gallery" / "rollout_text.png")) is not None
    if tmp_path / "gallery" / "rerun_rollout.png" not in written:
        with pytest.raises(ViewerUnavailable) as why:
            screenshot_recording(demo / "rollout_action" / "rollout.rrd", tmp_path / "shot.png")
        pytest.skip(f"headless Rerun viewer unavailable here: {why.value}")
    shot = cv2.imread(str(tmp_path / "gallery" / "rerun_rollout.png"))
    assert max(shot.shape[:2]) == 1280
    # the rollout's views are painted, not an empty viewer: its video and token views are full of colour
    assert shot.std() > 20 and len(np.unique(shot.reshape(-1, 3), axis=0)) > 1000


def test_gallery_of_the_showcase_copies_its_strips(checkpoints, tmp_path: Path) -> None:
    demo = tmp_path / "demo"
    run(checkpoints, demo / "showcase", "mode=showcase", "seconds=0.5", decoder=False)
    written = make_gallery(demo, tmp_path / "gallery")
    assert written[:2] == [tmp_path / "gallery" / "commands.png", tmp_path / "gallery" / "prompts.png"]
    commands = cv2.imread(str(written[0]))
    assert commands.shape == cv2.imread(str(demo / "showcase" / "commands" / "strip.png")).shape
    assert commands.shape[0] == 6 * 2 * 32  # real continuation raw and tokenized + 4 commands, 2× upscaled


def test_evaluate_mode_scores_model_ceiling_and_floor(checkpoints, tmp_path: Path) -> None:
    results = run(checkpoints, tmp_path, "mode=evaluate", "evaluate.contexts=3", "seconds=0.5",
                  "evaluate.probe_clips=2", "evaluate.probe_steps=2")
    assert set(results["rows"]) == {"model (video rollouts)", "tokens (real continuation, tokenized and rendered)",
                                    "held frame (last context frame repeated)"}
    for row in results["rows"].values():
        assert set(row) == {"psnr", "ssim", "fvmd", "agent_iou"} and np.isfinite(list(row.values())).all()
    assert 0 <= results["agent_probe"]["iou_on_real_future"] <= 1
    assert results["generated_frames"] == 4 and results["contexts"] == 3
    table = (tmp_path / "evaluation.md").read_text()
    assert "| model (video rollouts) |" in table and "fvmd ↓" in table
    assert json.loads((tmp_path / "evaluation.json").read_text())["rows"] == results["rows"]


@pytest.mark.parametrize(("overrides", "match"), [
    (["evaluate.metrics=[fvd]"], r"evaluate.metrics=\['fvd'\]: choose from"),
    (["evaluate.metrics=[fid]"], "set evaluate.fid_checkpoint"),
    (["evaluate.metrics=[fdd]"], "set evaluate.fdd_checkpoint"),
    (["evaluate.contexts=1"], "at least 2 clips per set"),
])
def test_evaluate_mode_bad_settings_fail_before_any_work(checkpoints, tmp_path: Path, overrides, match) -> None:
    with pytest.raises(ValueError, match=match):
        run(checkpoints, tmp_path, "mode=evaluate", *overrides)
    assert_no_outputs(tmp_path)


def test_evaluate_scores_a_perfect_future_perfectly_and_a_frozen_one_worse() -> None:
    from gaia_app.protocols.fidelity import score

    g = torch.Generator().manual_seed(0)
    base = torch.nn.functional.avg_pool2d(torch.rand(4, 3, 40, 72, generator=g) * 2 - 1, 5, 1, 2)
    real = torch.stack([torch.roll(base, shifts=(0, 2 * i), dims=(-2, -1))[:, :, 4:36, 4:68] for i in range(6)], dim=1)
    frozen = torch.cat([real[:, :2], real[:, 1:2].expand(-1, 4, -1, -1, -1)], dim=1)
    perfect = score(["psnr", "ssim", "fvmd"], real, real, t0=2)
    worse = score(["psnr", "ssim", "fvmd"], real, frozen, t0=2)
    assert (perfect["ssim"] == pytest.approx(1.0) and perfect["fvmd"] == pytest.approx(0.0, abs=1e-9)
            and perfect["psnr"] > 90)
    assert worse["psnr"] < 30 and worse["ssim"] < 0.9 and worse["fvmd"] > 0.1


def test_staging_replaces_the_folders_of_an_earlier_run_and_leaves_them_on_error(tmp_path: Path) -> None:
    """A second run into the same run dir (make demo twice) replaces its output folders whole."""
    for text in ("first", "second"):
        with staging(tmp_path) as stage:
            (stage / "commands").mkdir()
            (stage / "commands" / f"{text}.png").write_text(text)
            (stage / "showcase.md").write_text(text)
    assert [p.name for p in (tmp_path / "commands").iterdir()] == ["second.png"]
    assert (tmp_path / "showcase.md").read_text() == "second"
    with pytest.raises(RuntimeError), staging(tmp_path) as stage:
        (stage / "commands").mkdir()
        raise RuntimeError("a failed run")
    assert [p.name for p in (tmp_path / "commands").iterdir()] == ["second.png"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["commands", "showcase.md"]  # no staging folder left


def test_decoder_blend_config_reaches_the_decoder_and_changes_its_frames(checkpoints, tmp_path: Path) -> None:
    """decoder_blend (GAIA-1 §5.2 eq. 4) from generate.py's config: p = 1 blends every step, p = 0 none."""
    from gaia_app.protocols.loading import load_pipeline

    def decoded(probability: float) -> tuple[object, torch.Tensor]:
        cfg = compose_config("generate", [*(f"{k}={v}" for k, v in checkpoints.items()), "decoder_steps=2",
                                          f"decoder_blend.probability={probability}", "extras.print_config=false",
                                          *SIZE], tmp_path / str(probability))
        decoder = load_pipeline(cfg).decoder
        # one training step leaves the zero-initialised temporal layers near zero: give them weight, so the image
        # denoiser (temporal layers off) and the video one differ as they do in a trained decoder
        for layer in decoder.net.temporal_layers():
            torch.nn.init.normal_(layer.out.weight, std=0.5, generator=torch.Generator().manual_seed(1))
        tokens = torch.randint(0, 512, (1, 7, 8, 12), generator=torch.Generator().manual_seed(0))
        return decoder.blend, decoder.decode(tokens, torch.Generator().manual_seed(0))

    blend, blended = decoded(1.0)
    none, plain = decoded(0.0)
    assert none is None and (blend.probability, blend.weight) == (1.0, 0.5)
    assert (blended - plain).abs().max() > 1e-4


def test_decoder_sampler_config_picks_ddim_or_the_one_step_mean(checkpoints, tmp_path: Path) -> None:
    from gaia_app.diffusion.samplers import DDIMSampler, OneStepMeanSampler
    from gaia_app.protocols.loading import load_pipeline

    def sampler(*overrides: str):
        cfg = compose_config("generate", [*(f"{k}={v}" for k, v in checkpoints.items()), "extras.print_config=false",
                                          *SIZE, *overrides], tmp_path)
        return load_pipeline(cfg).decoder.sampler

    assert isinstance(sampler(), DDIMSampler) and sampler().steps == 50  # GAIA-1 §5.2
    mean = sampler("decoder_sampler=one_step_mean", "decoder_steps=3")
    assert isinstance(mean, OneStepMeanSampler) and mean.draws == 3 and not mean.antithetic
    pairs = sampler("decoder_sampler=antithetic_mean", "decoder_steps=4")
    assert isinstance(pairs, OneStepMeanSampler) and pairs.draws == 4 and pairs.antithetic
    with pytest.raises(ValueError, match="decoder_sampler: expected one of"):
        sampler("decoder_sampler=euler")
