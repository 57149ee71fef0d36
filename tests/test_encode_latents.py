"""generate.py mode=encode: a trained GAIA-2 video tokenizer writes a resumable, atomic latent cache of
multi-camera clips with every condition beside the latents (GAIA-2 report, tokenizer: the world model trains on
latents)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.utils import instantiate

import gaia_app.utils.run_dir as run_dir_module
from gaia_app.data.latent_cache import find_latent_clips, read_latent_clip
from gaia_app.data.transforms import to_float
from gaia_app.lit.checkpoint import load_module
from gaia_app.tasks.component_modes import read_in_order
from gaia_app.tasks.generate import generate
from tests.conftest import compose_config

# 8 train + 2 val 3-camera clips of 10 frames at 12.5 Hz: 2 whole latent steps of τ = 4 each
ENCODE = ["mode=encode", "data=synthetic_rig_tiny", "extras.print_config=false"]


@pytest.fixture(scope="module")
def ckpt(gaia2_tiny: dict[str, Path]) -> Path:
    """The 2-step tiny video tokenizer of the GAIA-2 chain (data=synthetic_rig_tiny), trained once per run."""
    return gaia2_tiny["tokenizer"]


def run_encode(ckpt: Path, run_dir: Path, out_dir: Path, *extra: str) -> dict:
    cfg = compose_config("generate", [*ENCODE, f"ckpt={ckpt}", f"out_dir={out_dir}", *extra], run_dir)
    return generate(cfg)["results"]


def test_encode_writes_latents_with_every_condition(ckpt: Path, tmp_path: Path) -> None:
    out = tmp_path / "latents"
    results = run_encode(ckpt, tmp_path / "g1", out)
    assert results["train"]["written"] == 8 and results["val"]["written"] == 2
    folders = find_latent_clips(out / "train")
    assert len(folders) == 8
    clip = read_latent_clip(folders[0])
    assert clip.mean.shape == (3, 2, 16, 8, 14)  # (v, t, C, h, w): 3 cameras, 8 of 10 frames → 2 steps, 64×112 / 8
    assert np.load(folders[0] / "mean.npy").dtype == np.float16
    assert clip.timestamps.shape == (8,) and np.allclose(np.diff(clip.timestamps), 1 / 12.5)
    assert clip.actions.shape == (8, 2) and len(clip.text) == 8 and len(clip.agents) == 8
    assert [c.name for c in clip.cameras] == ["front", "front_left", "front_right"]
    assert all((c.width, c.height) == (112, 64) for c in clip.cameras)
    assert clip.image_size == (64, 112) and clip.temporal_downsampling == 4 and clip.fps == pytest.approx(12.5)
    assert {"weather", "time_of_day"} <= set(clip.meta)


def test_cached_latents_are_the_tokenizers_posterior(ckpt: Path, tmp_path: Path) -> None:
    """The cache holds the encoder's mean and log-variance of the clip (to float16 precision)."""
    out = tmp_path / "latents"
    cfg = compose_config("generate", [*ENCODE, f"ckpt={ckpt}", f"out_dir={out}", "splits=[val]"], tmp_path / "g1")
    generate(cfg)
    datamodule = instantiate(cfg.data)
    datamodule.setup("fit")
    source = datamodule.val_clips[0]
    clip = read_latent_clip(out / "val" / source.clip_id)
    video = to_float(torch.from_numpy(source.frames[:, :8]))  # the first 2 whole latent steps of 10 frames
    with torch.no_grad():
        posterior = load_module(ckpt).tokenizer.encode(video[None])
    np.testing.assert_allclose(clip.mean, posterior.mean[0].numpy(), atol=2e-2, rtol=1e-2)
    np.testing.assert_allclose(clip.logvar, posterior.logvar[0].numpy(), atol=2e-2, rtol=1e-2)


def test_encode_with_the_shipped_tokenizer(tmp_path: Path) -> None:
    """weights=gaia2 encodes with the shipped video tokenizer (a cache to fine-tune the shipped world model on,
    model.init_from=gaia2): its posterior, and weights with ckpt is refused."""
    from gaia_app.weights.folders import load_nets, shipped_folder

    out = tmp_path / "latents"
    cfg = compose_config("generate", [*ENCODE, "weights=gaia2", f"out_dir={out}", "splits=[val]", "max_clips=1"],
                         tmp_path / "g1")
    assert generate(cfg)["results"]["val"]["written"] == 1
    datamodule = instantiate(cfg.data)
    datamodule.setup("fit")
    source = datamodule.val_clips[0]
    clip = read_latent_clip(out / "val" / source.clip_id)
    video = to_float(torch.from_numpy(source.frames[:, :8]))
    with torch.no_grad():
        posterior = load_nets(shipped_folder("gaia2"), "video_tokenizer")[0]["net"].encode(video[None])
    np.testing.assert_allclose(clip.mean, posterior.mean[0].numpy(), atol=2e-2, rtol=1e-2)
    with pytest.raises(ValueError, match="weights=gaia2 replaces ckpt=.*give one of them"):
        run_encode(Path("some.ckpt"), tmp_path / "g2", out, "weights=gaia2")


def test_clips_read_by_worker_processes_give_the_same_cache(ckpt: Path, tmp_path: Path) -> None:
    """workers=2 renders the clips in background processes: same clips, same order, same latents as workers=0."""
    here = run_encode(ckpt, tmp_path / "g1", tmp_path / "here", "splits=[train]", "max_clips=4")
    ahead = run_encode(ckpt, tmp_path / "g2", tmp_path / "ahead", "splits=[train]", "max_clips=4", "workers=2")
    assert here["train"]["written"] == ahead["train"]["written"] == 4
    folders = find_latent_clips(tmp_path / "here" / "train")
    assert [f.name for f in folders] == [f.name for f in find_latent_clips(tmp_path / "ahead" / "train")]
    for folder in folders:
        np.testing.assert_array_equal(np.load(folder / "mean.npy"),
                                      np.load(tmp_path / "ahead" / "train" / folder.name / "mean.npy"))


class WhoReads:
    """Item i → (i, the id of the process that read it)."""

    def __len__(self) -> int:
        return 6

    def __getitem__(self, i: int) -> tuple[int, int]:
        return i, os.getpid()


def test_worker_processes_read_the_clips_in_order() -> None:
    read = list(read_in_order(WhoReads(), 5, 2))
    assert [i for i, _ in read] == [0, 1, 2, 3, 4]
    assert os.getpid() not in {pid for _, pid in read}
    assert {pid for _, pid in read_in_order(WhoReads(), 3, 0)} == {os.getpid()}


def test_encode_refuses_a_negative_worker_count(ckpt: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"workers=-1: expected an integer in \[0, 256\]"):
        run_encode(ckpt, tmp_path / "g1", tmp_path / "latents", "splits=[train]", "workers=-1")


def test_encode_resumes_and_skips_finished_clips(ckpt: Path, tmp_path: Path) -> None:
    out = tmp_path / "latents"
    run_encode(ckpt, tmp_path / "g1", out, "max_clips=3", "splits=[train]")
    first = {p: p.stat().st_mtime_ns for p in (out / "train").rglob("*.npy")}
    results = run_encode(ckpt, tmp_path / "g2", out, "splits=[train]")
    assert results["train"] == {"written": 5, "skipped": 3, "out_dir": str(out / "train")}
    assert all(p.stat().st_mtime_ns == t for p, t in first.items())


def test_interrupted_write_leaves_an_unfinished_clip_that_is_redone(ckpt: Path, tmp_path: Path, monkeypatch) -> None:
    out = tmp_path / "latents"
    real_save = np.save
    calls = {"n": 0}

    def save_then_die(f, array):
        calls["n"] += 1
        if calls["n"] == 3:  # the first clip's log-variance: half-written, then the process "dies"
            f.write(b"\x93NUMPY partial")
            raise KeyboardInterrupt
        real_save(f, array)

    monkeypatch.setattr(run_dir_module.np, "save", save_then_die)
    with pytest.raises(KeyboardInterrupt):
        run_encode(ckpt, tmp_path / "g1", out, "splits=[train]")
    monkeypatch.undo()
    clip_dir = next(p for p in (out / "train").iterdir() if p.is_dir())  # beside it: the cache's cache.json
    assert not (clip_dir / "mean.npy").exists() and not (clip_dir / "logvar.npy").exists()
    assert not [p for p in clip_dir.iterdir() if p.name.startswith(".") or p.suffix == ".tmp"]
    with pytest.raises(Exception, match="no finished clip folders"):
        find_latent_clips(out / "train")
    results = run_encode(ckpt, tmp_path / "g2", out, "splits=[train]")
    assert results["train"]["written"] == 8
    read_latent_clip(clip_dir)


def test_encode_needs_a_gaia2_tokenizer_checkpoint(tiny_tokenizer_ckpt: Path, tmp_path: Path) -> None:
    with pytest.raises(TypeError, match=r"mode=encode: ckpt=.* holds a tokenizer \(ImageTokenizerModule\) "
                                        "checkpoint, expected a video_tokenizer checkpoint"):
        run_encode(tiny_tokenizer_ckpt, tmp_path / "g", tmp_path / "latents")


def test_pipeline_reconstructs_whole_latent_steps_of_a_clip() -> None:
    """10 frames at τ = 4: the first 8 are coded (whole steps); reconstruction = decode(posterior mean), clamped."""
    from gaia_app.data.synthetic import SyntheticClipDataset
    from gaia_app.pipelines.gaia2_video_tokenizer import VideoTokenizerPipeline
    from tests.models.test_gaia2_video_tokenizer import SMALL, VideoTokenizer

    torch.manual_seed(0)
    tokenizer = VideoTokenizer(**SMALL)
    clip = SyntheticClipDataset(num_clips=1, height=64, width=112, cameras=2, clip_len=10, fps=12.5)[0]
    out = VideoTokenizerPipeline(tokenizer, 32, 64).reconstruct(clip)
    assert out.video.shape == out.reconstruction.shape == (2, 8, 3, 32, 64)
    with torch.no_grad():
        expected = tokenizer.decode(tokenizer.encode(out.video[None]).mean)[0].clamp(-1, 1)
    torch.testing.assert_close(out.reconstruction, expected)
    assert out.reconstruction.abs().max() <= 1
