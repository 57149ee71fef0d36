"""The shipped GAIA-2 reference weights (gaia_app/weights/gaia2): the files its MANIFEST lists, a tokenizer that
reconstructs held-out synthetic clips, and the demo's rollout with a car cut in ahead, from the weights alone."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from gaia_app.data.synthetic import SyntheticClipDataset
from gaia_app.data.transforms import to_float
from gaia_app.eval.metrics import psnr
from gaia_app.pipelines.gaia2 import Gaia2Pipeline
from gaia_app.tasks.generate import generate
from gaia_app.weights.folders import WEIGHTS_ROOT
from tests.conftest import compose_config

pytestmark = pytest.mark.usefixtures("one_thread")

FOLDER = WEIGHTS_ROOT / "gaia2"
CAMERAS = ["front", "front_left", "front_right"]


def test_the_manifest_lists_every_shipped_file_with_its_size() -> None:
    listed = dict(re.findall(r"^\| gaia2/(\S+) \| (\d+) \|$", (FOLDER / "MANIFEST.md").read_text(), re.MULTILINE))
    shipped = {p.name: str(p.stat().st_size) for p in FOLDER.iterdir() if p.suffix in (".safetensors", ".yaml")}
    assert listed == shipped and len(shipped) == 4
    assert sum(int(n) for n in shipped.values()) < 25e6  # the size budget for GAIA-2


def test_the_shipped_tokenizer_reconstructs_held_out_clips() -> None:
    """Two clips of a world the tokenizer never saw (seed 777), every camera: mean PSNR above 21 dB (measured over
    16 clips: 24.2 dB; the earlier 600-step CPU tokenizer: 21.8 dB)."""
    pipeline = Gaia2Pipeline.from_weights("gaia2")
    world = SyntheticClipDataset(num_clips=2, seed=777, height=64, width=112, cameras=CAMERAS, clip_len=8, fps=12.5)
    scores = []
    for clip in (world[0], world[1]):
        frames = to_float(torch.from_numpy(clip.frames))  # (v, T, 3, H, W)
        with torch.no_grad():
            latents = pipeline.tokenizer.encode(frames[None]).mean
            video = pipeline.tokenizer.decode(latents)[0].clamp(-1, 1)
        scores.append(psnr(video.flatten(0, 1), frames.flatten(0, 1)).mean())
    assert float(torch.stack(scores).mean()) > 21.0


def test_the_demo_rollout_cuts_a_car_in_ahead_from_the_weights_alone(tmp_path: Path) -> None:
    car = "model.add_agents=[{category: car, centre: [9, 0, 0.75], size: [4.5, 1.9, 1.5]}]"
    cfg = compose_config("generate", ["model=gaia2", "mode=rollout", "weights=gaia2", "data=synthetic_rig",
                                      "model.chunks=1", "model.sampler.steps=4", "model.sampler.progress=false",
                                      "num_futures=1", "model.guidance.scale=3", car, "extras.print_config=false"],
                         tmp_path)
    results = generate(cfg)["results"]
    assert results["cameras"] == 3 and results["first_generated_frame"] == 8
    conditioning = json.loads((tmp_path / "conditioning.json").read_text())
    assert conditioning["added_agents"][0]["centre"] == [9, 0, 0.75]
    latents = np.load(tmp_path / "latents.npy")
    assert latents.shape[:3] == (1, 3, 4) and np.isfinite(latents).all()
    assert {"sample_0.mp4", "grid.mp4", "rollout.rrd"} <= {p.name for p in tmp_path.iterdir()}


def test_fine_tuning_the_shipped_world_model_end_to_end(tmp_path: Path) -> None:
    """The documented fine-tune chain from the shipped weights alone: encode with the shipped tokenizer
    (weights=gaia2), experiment=gaia2/world_model_finetune (init_from=gaia2), export beside the shipped tokenizer,
    generate from the new folder. The fine-tune starts at the shipped net: its first validation loss is the shipped
    model's, far under a fresh net's."""
    from gaia_app.tasks.train import train

    rig = ["data=synthetic_rig_tiny", "extras.print_config=false"]
    latents = tmp_path / "latents"
    generate(compose_config("generate", ["mode=encode", "weights=gaia2", *rig, f"out_dir={latents}", "max_clips=2"],
                            tmp_path / "encode"))
    losses = {}
    for name, start in (("tuned", []), ("fresh", ["model.init_from=null"])):
        run = tmp_path / name
        train(compose_config("train", ["experiment=gaia2/world_model_finetune", "trainer=tiny", *rig[1:],
                                       f"data.path={latents}", "data.steps=2", "data.batch_size=2",
                                       "data.num_workers=0", "trainer.max_steps=1", "trainer.val_check_interval=1",
                                       "logger=csv", *start],
                             run))
        metrics = next(run.rglob("metrics.csv")).read_text().splitlines()
        header = metrics[0].split(",")
        column = header.index("val/loss")
        losses[name] = next(float(row.split(",")[column]) for row in metrics[1:] if row.split(",")[column])
    assert losses["tuned"] < 0.5 * losses["fresh"]
    folder = tmp_path / "weights"
    generate(compose_config("generate", ["model=gaia2", "mode=export", "weights=gaia2", *rig, f"out_dir={folder}",
                                         f"world_model_ckpt={tmp_path / 'tuned' / 'checkpoints' / 'last.ckpt'}"],
                            tmp_path / "export"))
    cfg = compose_config("generate", ["model=gaia2", "mode=scratch", f"weights={folder}", *rig, "model.steps=2",
                                      "model.context_steps=1", "model.sampler.steps=2", "model.sampler.progress=false",
                                      "num_futures=1"],
                         tmp_path / "generate")
    generate(cfg)
    assert np.isfinite(np.load(tmp_path / "generate" / "latents.npy")).all()
