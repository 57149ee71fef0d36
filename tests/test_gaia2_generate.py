"""generate.py model=gaia2: every GAIA-2 inference mode and the evaluation end to end on tiny checkpoints
(GAIA-2 report, inference and evaluation)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from hydra.utils import instantiate
from rerun.chunk import RrdReader

from gaia_app.data.clip import AgentBoxes
from gaia_app.data.latent_cache import find_latent_clips, read_latent_clip
from gaia_app.eval.report import combined_table
from gaia_app.pipelines.gaia1_inputs import future_actions
from gaia_app.pipelines.gaia2 import Gaia2Pipeline, check_metadata, with_labels
from gaia_app.pipelines.gaia2_edits import with_added_agents
from gaia_app.protocols.gaia2_evaluate import box_masks
from gaia_app.tasks.gaia2_generate import left_to_right, pixel_boxes
from gaia_app.tasks.generate import generate
from gaia_app.tasks.train import train
from tests.conftest import compose_config

pytestmark = pytest.mark.usefixtures("one_thread")

RIG = ["data=synthetic_rig_tiny", "extras.print_config=false"]


@pytest.fixture(scope="module")
def checkpoints(gaia2_tiny: dict[str, Path]) -> dict[str, Path]:
    """The tiny GAIA-2 chain of tests/tiny_checkpoints.py, trained once for the whole run."""
    return gaia2_tiny


def run(checkpoints: dict[str, Path], run_dir: Path, mode: str, *extra: str) -> dict:
    cfg = compose_config("generate", ["model=gaia2", f"mode={mode}", *RIG, f"tokenizer_ckpt={checkpoints['tokenizer']}",
                                      f"world_model_ckpt={checkpoints['world_model']}", "model.sampler.steps=3",
                                      "model.sampler.progress=false", "num_futures=1", *extra], run_dir)
    return generate(cfg)["results"]


def recording_rows(path: Path) -> dict[str, int]:
    rows: dict[str, int] = {}
    for chunk in RrdReader(str(path)).stream().collect().stream().to_chunks():
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    return rows


@pytest.mark.parametrize("mode", ["scratch", "rollout", "inpaint", "edit"])
def test_every_mode_runs_end_to_end(checkpoints, tmp_path: Path, mode: str) -> None:
    results = run(checkpoints, tmp_path, mode, "model.chunks=2")
    steps = 6 if mode == "rollout" else 4  # rollout: 2 context + 2 chunks × 2 new steps
    assert results["latent_steps"] == steps and results["frames"] == 4 * steps and results["cameras"] == 3
    assert sorted(results["files"]) == sorted(["sample_0.mp4", "grid.mp4", "rollout.rrd", "latents.npy",
                                               "conditioning.json"])
    assert {p.name for p in tmp_path.iterdir()} >= set(results["files"]) and not list(tmp_path.glob(".rollout-*"))
    latents = np.load(tmp_path / "latents.npy")
    assert latents.shape == (1, 3, steps, 16, 8, 14) and latents.dtype == np.float16 and np.isfinite(latents).all()
    rows = recording_rows(tmp_path / "rollout.rrd")
    for root in ("/real", "/sample_0"):
        for camera in ("front", "front_left", "front_right"):
            assert rows[f"{root}/ego/rig/{camera}"] >= 4 * steps  # frames (+ the static pinhole and pose)
        assert rows[f"{root}/ego/agents"] == 4 * steps and rows[f"{root}/actions/speed"] == 4 * steps
        assert f"{root}/ego/rig/front/boxes" in rows and f"{root}/text" in rows


def clip_latents(checkpoints: dict[str, Path], frames: int = 16) -> np.ndarray:
    """(v, t, C, h, w) posterior means of the default context clip (clip 0 of the world context.seed)."""
    cfg = compose_config("generate", RIG, Path("unused"))
    world = instantiate(cfg.data.source, num_clips=1, seed=cfg.context.seed, clip_len=frames)
    pipeline = Gaia2Pipeline.from_checkpoints(checkpoints["tokenizer"], checkpoints["world_model"], 64, 112)
    return pipeline.encode(world[0]).mean


def test_rollout_keeps_the_context_and_follows_commanded_actions(checkpoints, tmp_path: Path) -> None:
    results = run(checkpoints, tmp_path, "rollout", "model.chunks=1", "speed=brake", "curvature=left")
    assert results["first_generated_frame"] == 8
    conditioning = json.loads((tmp_path / "conditioning.json").read_text())
    actions = np.array(conditioning["actions"])
    expected = future_actions("brake", "left", 8, 12.5, float(actions[7, 0]))
    np.testing.assert_allclose(actions[8:], expected, atol=1e-4)
    latents = np.load(tmp_path / "latents.npy").astype(np.float32)
    np.testing.assert_allclose(latents[0, :, :2], clip_latents(checkpoints)[:, :2], atol=2e-2)  # float16 on disk
    assert np.abs(latents[0, :, 2:] - clip_latents(checkpoints)[:, 2:]).max() > 0.1


def test_inpainting_a_box_keeps_the_rest_of_the_clip(checkpoints, tmp_path: Path) -> None:
    run(checkpoints, tmp_path, "inpaint", "model.inpaint.region=box", "model.inpaint.box=[0.5,0.5,1.0,1.0]",
        "model.inpaint.cameras=[front_left]")
    latents = np.load(tmp_path / "latents.npy").astype(np.float32)[0]
    real = clip_latents(checkpoints)
    # outside the box (front_left, rows ≥ 4 and columns ≥ 7 of the 8×14 grid) the sample is the clip
    outside = np.ones(latents.shape, dtype=bool)
    outside[1, :, :, 4:, 7:] = False
    np.testing.assert_allclose(latents[outside], real[outside], atol=2e-2)
    assert np.abs(latents[~outside] - real[~outside]).max() > 0.1


def test_gaia2_from_a_latent_cache_with_fewer_cameras_than_training(checkpoints, tmp_path: Path) -> None:
    """A cached clip of the latent cache as the context, and a 2-camera rig for a model trained on 3."""
    cached = run(checkpoints, tmp_path / "cache", "rollout", "context.source=latents", "model.chunks=1",
                 f"context.folder={checkpoints['latents'] / 'val'}", "context.index=1")
    assert cached["clip"] == read_latent_clip(find_latent_clips(checkpoints["latents"] / "val")[1]).clip_id
    two = run(checkpoints, tmp_path / "two", "scratch", "data.source.cameras=[front_left,front]")
    assert two["cameras"] == 2
    assert json.loads((tmp_path / "two" / "conditioning.json").read_text())["cameras"] == ["front_left", "front"]


def test_bad_gaia2_settings_are_named(checkpoints, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="model.metadata.weather='hail'"):
        run(checkpoints, tmp_path / "a", "scratch", "model.metadata={weather: hail}")
    with pytest.raises(ValueError, match="model.metadata.colour"):
        run(checkpoints, tmp_path / "b", "scratch", "model.metadata={colour: red}")
    with pytest.raises(ValueError, match="model=gaia2 mode=video"):
        run(checkpoints, tmp_path / "c", "video")
    with pytest.raises(ValueError, match="world_model_ckpt"):
        generate(compose_config("generate", ["model=gaia2", "mode=scratch", *RIG, "tokenizer_ckpt=x.ckpt"],
                                tmp_path / "d"))
    with pytest.raises(TypeError, match="world_model_ckpt=.*VideoTokenizerModule"):
        generate(compose_config("generate", ["model=gaia2", "mode=scratch", *RIG,
                                             f"tokenizer_ckpt={checkpoints['tokenizer']}",
                                             f"world_model_ckpt={checkpoints['tokenizer']}"], tmp_path / "e"))
    with pytest.raises(ValueError, match="inpaint.cameras"):
        run(checkpoints, tmp_path / "f", "inpaint", "model.inpaint.region=box", "model.inpaint.cameras=[rear]")
    with pytest.raises(ValueError, match="model.evaluate.action_agents='boxes'"):
        run(checkpoints, tmp_path / "h", "evaluate", "model.evaluate.action_agents=boxes")
    with pytest.raises(ValueError, match="not a trainable model"):
        train(compose_config("train", ["model=gaia2", "extras.print_config=false"], tmp_path / "g"))
    assert not (tmp_path / "a" / "results.json").exists()


def test_edited_labels_reach_the_conditions(checkpoints) -> None:
    clip = read_latent_clip(find_latent_clips(checkpoints["latents"] / "val")[0])
    pipeline = Gaia2Pipeline.from_checkpoints(checkpoints["tokenizer"], checkpoints["world_model"], 64, 112)
    edited = with_labels(clip, 8, np.full((8, 2), [3.0, 0.02], np.float32), "It is snowing.", {"weather": "snow"})
    _, cond = pipeline.window(edited, 0, 4)
    _, original = pipeline.window(clip, 0, 4)
    torch.testing.assert_close(cond.actions[0, 2:], torch.tensor([[3.0, 0.02]] * 2))
    torch.testing.assert_close(cond.actions[0, :2], original.actions[0, :2])
    assert int(cond.metadata["weather"][0]) == 4 and not torch.equal(cond.text, original.text)
    check_metadata({"weather": "snow", "speed_limit": 50}, ["weather", "speed_limit"])


def test_conditioning_boxes_project_onto_the_camera_that_sees_them(checkpoints) -> None:
    clip = read_latent_clip(find_latent_clips(checkpoints["latents"] / "val")[0])
    ahead = AgentBoxes(centre=[[12.0, 0.0, 0.8]], size=[[4.5, 1.9, 1.6]], yaw=[0.0], category=[0], track_id=[7])
    clip.agents = [ahead] * len(clip.agents)
    assert [clip.cameras[i].name for i in left_to_right(clip)] == ["front_left", "front", "front_right"]
    boxes = pixel_boxes(clip)
    front = boxes[0]["boxes_2d"]["front"]
    assert len(front) == 1 and front[0]["track_id"] == 7 and front[0]["category"] == "car"
    x0, y0, x1, y1 = front[0]["box"]
    assert 0 < x0 < 56 < x1 < 112 and 0 < y0 < y1 <= 64  # centred in the 112-wide front view
    pipeline = Gaia2Pipeline.from_checkpoints(checkpoints["tokenizer"], checkpoints["world_model"], 64, 112)
    _, cond = pipeline.window(clip, 0, 4)
    masks = box_masks(cond, 16, 4)
    assert masks.shape == (3, 16, 64, 112) and masks[0].any() and masks[0, :, 32, 56].all()
    assert masks[0].sum() == 16 * int(masks[0, 0].sum())


CAR_AHEAD = "model.add_agents=[{category: car, centre: [10, 0, 0.75], size: [4.5, 1.9, 1.5], velocity: [-2, 0]}]"


def test_a_car_added_ahead_conditions_the_generated_steps_only(checkpoints, tmp_path: Path) -> None:
    """model.add_agents (an edited scene): a rollout gets the new car on its generated frames, moving at its relative
    velocity, under a new track id; the context keeps the clip's own agents; the front camera sees it."""
    run(checkpoints, tmp_path, "rollout", "model.chunks=1", CAR_AHEAD)
    conditioning = json.loads((tmp_path / "conditioning.json").read_text())
    assert conditioning["added_agents"][0]["category"] == "car"
    clip = read_latent_clip(find_latent_clips(checkpoints["latents"] / "val")[0])
    pipeline = Gaia2Pipeline.from_checkpoints(checkpoints["tokenizer"], checkpoints["world_model"], 64, 112)
    spec = {"category": "car", "centre": [10, 0, 0.75], "size": [4.5, 1.9, 1.5], "velocity": [-2, 0]}
    edited = with_added_agents(clip, [spec], 8)
    own = max(int(a.track_id.max()) for a in clip.agents if len(a))
    for f in range(16):
        assert len(edited.agents[f]) == len(clip.agents[f]) + (f >= 8)
    car = edited.agents[8:]
    dt = clip.timestamps[15] - clip.timestamps[8]
    assert car[0].track_id[-1] == car[-1].track_id[-1] == own + 1
    np.testing.assert_allclose(car[-1].centre[-1], [10 - 2 * dt, 0, 0.75], atol=1e-5)
    front = pixel_boxes(edited)[8]["boxes_2d"]["front"]
    assert any(box["track_id"] == own + 1 for box in front)
    _, cond = pipeline.window(edited, 0, 4)
    _, original = pipeline.window(clip, 0, 4)
    given, own_count = cond.agents.mask[0].sum(-1), original.agents.mask[0].sum(-1)  # agents per latent step
    assert torch.equal(given[:2], own_count[:2]) and torch.equal(given[2:], own_count[2:] + 1)


def test_bad_added_agents_are_named(checkpoints, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"model.add_agents\[0\].category='tank'"):
        run(checkpoints, tmp_path / "a", "scratch",
            "model.add_agents=[{category: tank, centre: [1,0,0], size: [1,1,1]}]")
    with pytest.raises(ValueError, match=r"model.add_agents\[0\]: unknown keys \['speed'\], missing keys \['size'\]"):
        run(checkpoints, tmp_path / "b", "scratch", "model.add_agents=[{category: car, centre: [1,0,0], speed: 3}]")
    with pytest.raises(ValueError, match=r"model.add_agents\[0\].centre=\[1, 0\]: expected 3 finite numbers"):
        run(checkpoints, tmp_path / "c", "scratch", "model.add_agents=[{category: car, centre: [1,0], size: [1,1,1]}]")
    with pytest.raises(ValueError, match=r"model.add_agents\[0\].size=.*must be positive"):
        run(checkpoints, tmp_path / "d", "scratch",
            "model.add_agents=[{category: car, centre: [1,0,0], size: [1,0,1]}]")


def test_gaia2_evaluation_writes_both_tables(checkpoints, tmp_path: Path) -> None:
    # model.steps=3: two context steps and one generated latent step (4 frames), half the rollouts
    results = run(checkpoints, tmp_path, "evaluate", "model.evaluate.contexts=2", "model.evaluate.probe_clips=2",
                  "model.evaluate.probe_steps=3", "model.steps=3", "model.evaluate.speed_probe=twin")
    assert set(results["agents"]["rows"]) == {"real frames", "tokenized real", "model, agent conditions",
                                              "model, plain CFG ×3", "model, selective CFG ×3",
                                              "model, selective CFG ×3, full second pass",
                                              "model, selective CFG ×3, paired agent passes", "model, agents dropped"}
    agents = results["agents"]["rows"]
    for name, row in agents.items():  # every IoU with its interval over scenes; the guided rows paired to plain CFG
        interval = row["iou_agent_masks_interval"]
        assert interval["n"] == 2 and interval["mean"] == row["iou_agent_masks"]
        assert ("iou_agent_masks_minus_plain" in row) == (name in {"model, selective CFG ×3",
                                                                   "model, selective CFG ×3, full second pass",
                                                                   "model, selective CFG ×3, paired agent passes"})
        assert 0 <= row["iou_inside_boxes"] <= 1 and 0 <= row["agent_share_outside_boxes"] <= 1
        assert ("agent_share_outside_boxes_minus_plain" in row) == ("iou_agent_masks_minus_plain" in row)
    # every model row other than the floor, paired with the floor by scene (the agent target's comparison)
    assert {n for n, row in agents.items() if "iou_agent_masks_minus_dropped" in row} == {
        n for n in agents if n.startswith("model, ") and n != "model, agents dropped"}
    given = agents["model, agent conditions"]["iou_agent_masks_minus_dropped"]["mean"]
    assert given == pytest.approx(agents["model, agent conditions"]["iou_agent_masks"]
                                  - agents["model, agents dropped"]["iou_agent_masks"])
    from gaia_app.protocols.gaia2_evaluate import agent_markdown

    under_table = agent_markdown(results["agents"], ["front"])[-1]
    assert under_table.startswith("IoU with agent masks minus the agents-dropped row, paired by scene")
    assert f"model, agent conditions {given:+.3f} [" in under_table and "model, agents dropped " not in under_table
    paired = agents["model, selective CFG ×3"]["iou_agent_masks_minus_plain"]["mean"]
    assert paired == pytest.approx(agents["model, selective CFG ×3"]["iou_agent_masks"]
                                   - agents["model, plain CFG ×3"]["iou_agent_masks"])
    actions = results["actions"]
    assert set(actions["rows"]) == {"ceiling", "tokenized", "model", "floor", "reference"}
    assert actions["contrasts"] == {"speed_contrast": ["accelerate/straight", "brake/straight"],
                                    "curvature_contrast": ["keep/left", "keep/right"]}
    assert set(actions["checks"]) == {"speed_contrast", "curvature_contrast"}
    views = results["cross_view"]
    assert views["pairs"] == ["front/front_left", "front/front_right"] and views["scenes"] == 2
    assert set(views["rows"]) == {"real frames (ceiling)", "tokenized real", "model, cameras generated together",
                                  "model, each camera generated alone (floor)"}
    assert all(0 <= row["mean"] < 2 and row["n"] == 2 for row in views["rows"].values())
    for row in results["actions"]["rows"].values():
        assert all(np.isfinite(row[m]["mean"]) and row[m]["n"] == 2 for m in ("speed_contrast", "curvature_contrast",
                                                                            "speed_mae", "curvature_mae"))
    fidelity = results["fidelity"]
    assert fidelity["clips"] == 6 and fidelity["context_frames"] == 8 and fidelity["generated_frames"] == 4
    assert set(fidelity["rows"]) == {"model (rollouts)", "tokenized real (ceiling)", "held frame (floor)"}
    assert all(set(row) == {"psnr", "ssim", "fvmd", "agent_iou"} for row in fidelity["rows"].values())
    table = (tmp_path / "gaia2_evaluation.md").read_text()
    assert "IoU with agent masks" in table and "speed contrast error" in table and "held frame (floor)" in table
    assert "agent masks − plain CFG" in table
    assert "| probe check: ceiling ≤ ½ floor and ≤ ½ reference |" in table
    assert "| model, each camera generated alone (floor) |" in table
    # 4 generated frames, the probe reads pairs 2 frames apart (model.evaluate.probe_stride): 2 pairs of generated
    # frames
    assert results["actions"]["probe_stride"] == 2 and results["actions"]["scored_steps"] == 2
    assert results["actions"]["probe_cameras"] == "rig" and "Action adherence (every camera of the rig," in table
    # the action probe is saved with the run, for later runs to load (model.evaluate.action_probe)
    saved = yaml.safe_load((tmp_path / "action_probe" / "action_probe.yaml").read_text())
    assert saved["probe_steps"] == 3 and saved["fit"] == results["probe_fit"]["action_probe"]
    # speed_probe=twin: the speed contrast read by the twin probe (saved too), the pair probe's kept beside it; the
    # floor's futures ignore the command, so the twin probe reads none of it
    twin = yaml.safe_load((tmp_path / "twin_probe" / "twin_probe.yaml").read_text())
    assert twin["fit"] == results["probe_fit"]["twin_probe"] and actions["speed_probe"] == "twin"
    floor = actions["rows"]["floor"]
    assert "speed_contrast_pair" in floor and floor["realised"]["speed_contrast"]["mean"] == 0
    assert "Speed contrast read by the twin probe" in table

    # one table with a GAIA-1 evaluation run (its evaluation.json layout, protocols/evaluate.py)
    gaia1 = tmp_path / "gaia1"
    gaia1.mkdir()
    row = {"psnr": 20.0, "ssim": 0.5, "fvmd": 3.0, "agent_iou": 0.2, "lpips": 0.3}
    (gaia1 / "evaluation.json").write_text(json.dumps({"contexts": 8, "context_frames": 2, "generated_frames": 7,
                                                       "rate": 6.25, "rows": {"model (video rollouts)": row}}))
    merged = combined_table({"GAIA-1": gaia1, "GAIA-2": tmp_path})
    assert merged.count("| GAIA-2 · ") == 3
    assert "| GAIA-1 · model (video rollouts) | 20.000 | 0.500 | 3.000 | 0.200 |" in merged
    assert "lpips" not in merged  # only the metrics both runs computed


def test_export_gives_a_weights_folder_that_generates_like_the_checkpoints(checkpoints, tmp_path: Path) -> None:
    """model=gaia2 mode=export → video_tokenizer.* + latent_world_model.*; `weights=` runs generate the same
    latents as the training checkpoints (float32 export: exactly; nothing but nets is stored)."""
    folder = tmp_path / "weights"
    exported = generate(compose_config("generate", ["model=gaia2", "mode=export", *RIG, "export_dtype=float32",
                                                    f"tokenizer_ckpt={checkpoints['tokenizer']}",
                                                    f"world_model_ckpt={checkpoints['world_model']}",
                                                    f"out_dir={folder}"], tmp_path / "export"))["results"]
    assert {p.name for p in folder.iterdir()} == {"video_tokenizer.safetensors", "video_tokenizer.yaml",
                                                  "latent_world_model.safetensors", "latent_world_model.yaml"}
    assert exported["latent_world_model"]["parameters"] > 0
    run(checkpoints, tmp_path / "ckpt", "scratch")
    cfg = compose_config("generate", ["model=gaia2", "mode=scratch", *RIG, f"weights={folder}", "model.sampler.steps=3",
                                      "model.sampler.progress=false", "num_futures=1"], tmp_path / "weights_run")
    generate(cfg)
    np.testing.assert_array_equal(np.load(tmp_path / "weights_run" / "latents.npy"),
                                  np.load(tmp_path / "ckpt" / "latents.npy"))
    with pytest.raises(ValueError, match="replaces tokenizer_ckpt"):
        generate(compose_config("generate", ["model=gaia2", "mode=scratch", *RIG, f"weights={folder}",
                                             f"tokenizer_ckpt={checkpoints['tokenizer']}"], tmp_path / "both"))
    with pytest.raises(ValueError, match=r"trained on \(64, 112\) frames"):
        generate(compose_config("generate", ["model=gaia2", "mode=scratch", *RIG, f"weights={folder}",
                                             "data.height=32"], tmp_path / "size"))
    with pytest.raises(TypeError, match=r"tokenizer_ckpt=.* holds a latent_world_model \(LatentWorldModelModule\)"):
        generate(compose_config("generate", ["model=gaia2", "mode=export", *RIG, f"out_dir={tmp_path / 'x'}",
                                             f"tokenizer_ckpt={checkpoints['world_model']}",
                                             f"world_model_ckpt={checkpoints['world_model']}"], tmp_path / "wrong"))


def test_export_keeps_the_tokenizer_of_a_weights_folder(checkpoints, tmp_path: Path) -> None:
    """A world model fine-tuned from shipped weights (model.init_from=gaia2) is exported beside their tokenizer:
    `weights=<folder>` copies its video tokenizer (also into the folder itself), and refuses tokenizer_ckpt too."""
    first = tmp_path / "first"
    generate(compose_config("generate", ["model=gaia2", "mode=export", *RIG,
                                         f"tokenizer_ckpt={checkpoints['tokenizer']}",
                                         f"world_model_ckpt={checkpoints['world_model']}", f"out_dir={first}"],
                            tmp_path / "e1"))
    for out in (tmp_path / "second", first):
        results = generate(compose_config("generate", ["model=gaia2", "mode=export", *RIG, f"weights={first}",
                                                       f"world_model_ckpt={checkpoints['world_model']}",
                                                       f"out_dir={out}"], tmp_path / f"e_{out.name}"))["results"]
        assert results["video_tokenizer"] == f"copied from {first}"
        assert results["latent_world_model"]["parameters"] > 0
    second = tmp_path / "second"
    for name in ("video_tokenizer.safetensors", "video_tokenizer.yaml"):
        assert (second / name).read_bytes() == (first / name).read_bytes()
    with pytest.raises(ValueError, match="gives the video tokenizer; drop tokenizer_ckpt"):
        generate(compose_config("generate", ["model=gaia2", "mode=export", *RIG, f"weights={first}",
                                             f"tokenizer_ckpt={checkpoints['tokenizer']}",
                                             f"world_model_ckpt={checkpoints['world_model']}",
                                             f"out_dir={tmp_path / 'x'}"], tmp_path / "both"))
    with pytest.raises(ValueError,
                       match=r"needs tokenizer_ckpt=<checkpoint of a GAIA-2 video tokenizer> \(or weights="):
        generate(compose_config("generate", ["model=gaia2", "mode=export", *RIG, f"out_dir={tmp_path / 'x'}",
                                             f"world_model_ckpt={checkpoints['world_model']}"], tmp_path / "none"))
    with pytest.raises(ValueError, match="model=gaia2 mode=export needs world_model_ckpt="):
        generate(compose_config("generate", ["model=gaia2", "mode=export", *RIG, f"weights={first}",
                                             f"out_dir={tmp_path / 'x'}"], tmp_path / "no_world_model"))


def test_inference_builds_nets_without_lightning_modules(checkpoints, tmp_path: Path) -> None:
    """Issue 23: GAIA-2 inference and the tokenizer modes build bare nets from checkpoints; no gaia_app.lit module
    (and so no LightningModule) is imported on the way (a fresh interpreter, so nothing is preloaded)."""
    import subprocess
    import sys

    script = (
        "import sys\n"
        "from gaia_app.pipelines.gaia2 import Gaia2Pipeline\n"
        "from gaia_app.weights.nets import checkpoint_nets\n"
        f"p = Gaia2Pipeline.from_checkpoints(r'{checkpoints['tokenizer']}', r'{checkpoints['world_model']}', 64, 112)\n"
        f"checkpoint_nets(r'{checkpoints['tokenizer']}', 'video_tokenizer', 'ckpt')\n"
        "import gaia_app.tasks.generate\n"
        "print(sorted(m for m in sys.modules if m.startswith('gaia_app.lit')))\n")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300,
                         cwd=Path(__file__).resolve().parents[1])
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "[]"
