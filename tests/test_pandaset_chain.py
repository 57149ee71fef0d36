"""Real multi-camera data through the whole GAIA-2 path (issue 22, item 2), on the PandaSet sequence of ../shared:
import → tokenizer reconstruction per camera → encode → a short world-model fine-tune (from a synthetic
pre-training) → a six-camera rollout with the real 3-D boxes projected in its Rerun recording.

The commands are those of docs/latent_world_model.md ("Real multi-camera data: PandaSet"), at 64×112 with tiny
networks trained for two steps: this checks the path, not quality. Skips when ../shared/data is absent.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from rerun.chunk import RrdReader

from gaia_app.data.importers.pandaset import import_pandaset
from gaia_app.data.latent_cache import find_latent_clips, read_latent_clip
from gaia_app.tasks.generate import generate
from gaia_app.tasks.train import train
from tests.conftest import compose_config

pytestmark = pytest.mark.usefixtures("one_thread")

CAMERAS = ["front", "front_left", "front_right", "left", "right", "back"]
TINY = ["trainer=tiny", "trainer.max_steps=2", "logger=csv", "extras.print_config=false"]
# the one imported sequence is both the training and the validation clip: this demonstrates the path, it measures
# nothing held out
REAL = ["data=video_folder", "data.height=64", "data.width=112", "data.fps=null", "data.val_source=${data.source}",
        "data.num_workers=0"]


@pytest.fixture
def sequence(shared_data: Path) -> Path:
    path = shared_data / "real" / "pandaset_002"
    if not path.is_dir():
        pytest.skip(f"{path} is absent")
    return path


def test_pandaset_goes_through_the_whole_gaia2_path(sequence: Path, gaia2_tiny: dict[str, Path],
                                                   tmp_path: Path) -> None:
    clips = tmp_path / "clips"
    clip_dir = import_pandaset(sequence, clips, height=64, width=112, progress=False)
    real = [f"data.source.root={clips}", *REAL]
    # pre-training on the synthetic rig: the suite's tiny video tokenizer, its latent cache and latent world model
    # (tests/tiny_checkpoints.py: build_gaia2, the documented commands at 2 steps each)
    tokenizer, synthetic_world_model = gaia2_tiny["tokenizer"], gaia2_tiny["world_model"]
    # the tokenizer on the real rig: PSNR per camera
    psnr = generate(compose_config("generate", ["mode=reconstruct", f"ckpt={tokenizer}", *real, "num_clips=1",
                                                "extras.print_config=false"], tmp_path / "rec"))["results"]
    assert list(psnr) == [clip_dir.name] and list(psnr[clip_dir.name]) == CAMERAS
    assert all(0 < row["psnr"] < 60 for row in psnr[clip_dir.name].values())
    assert (tmp_path / "rec" / f"{clip_dir.name}_back.mp4").is_file()

    # encode → fine-tune from the synthetic world model (six cameras where it was trained on three)
    generate(compose_config("generate", ["mode=encode", f"ckpt={tokenizer}", *real, f"out_dir={tmp_path / 'latents'}",
                                         "extras.print_config=false"], tmp_path / "enc"))
    latent = read_latent_clip(find_latent_clips(tmp_path / "latents" / "val")[0])
    assert [c.name for c in latent.cameras] == CAMERAS and latent.agents is not None and latent.actions is not None
    train(compose_config("train", ["experiment=gaia2/world_model_tiny", f"data.path={tmp_path / 'latents'}",
                                   "data.batch_size=1",
                                   f"model.init_from={synthetic_world_model}", *TINY],
                         tmp_path / "wm"))

    # a six-camera rollout from the real context, its boxes projected into every camera in the recording
    results = generate(compose_config("generate", [
        "model=gaia2", "mode=rollout", "context.source=latents", f"context.folder={tmp_path / 'latents' / 'val'}",
        f"tokenizer_ckpt={tokenizer}", f"world_model_ckpt={tmp_path / 'wm' / 'checkpoints' / 'last.ckpt'}",
        "data.height=64", "data.width=112", "model.sampler.steps=2", "model.sampler.progress=false", "num_futures=1",
        "model.chunks=1", "extras.print_config=false"], tmp_path / "rollout"))["results"]
    assert results["cameras"] == 6
    entities = {chunk.entity_path for chunk in RrdReader(str(tmp_path / "rollout" / "rollout.rrd")).stream().collect()
                .stream().to_chunks()}
    for camera in CAMERAS:
        assert f"/real/ego/rig/{camera}/boxes" in entities or f"/sample_0/ego/rig/{camera}/boxes" in entities
