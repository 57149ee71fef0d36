"""`generate(cfg)`: run a trained checkpoint on clips and write mp4s, tokens, metrics and a .rrd."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import rerun as rr
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig
from tqdm import tqdm

from gaia_app.data.datasets import fit_to_resolution
from gaia_app.data.transforms import to_float, to_uint8
from gaia_app.data.video_io import write_video
from gaia_app.lit.checkpoint import load_module
from gaia_app.lit.gaia1_tokenizer import ImageTokenizerModule
from gaia_app.pipelines.gaia1_tokenizer import ReconstructionOutput, TokenizerReconstructionPipeline
from gaia_app.utils.run_dir import atomic_write_text, save_resolved_config
from gaia_app.viz.media import log_token_map, to_hwc_uint8

log = logging.getLogger(__name__)


def side_by_side(a: torch.Tensor, b: torch.Tensor) -> np.ndarray:
    """(t, 3, H, W) ×2 in [-1, 1] → (t, H, 2W, 3) uint8 frames, a left of b."""
    both = torch.cat([a, b], dim=-1)
    return to_uint8(both).permute(0, 2, 3, 1).contiguous().numpy()


def log_reconstruction(rec: rr.RecordingStream, name: str, camera: str, video: torch.Tensor, out: ReconstructionOutput,
                       view: int, codebook: torch.Tensor) -> None:
    """Input, reconstruction, token map and per-frame PSNR of one camera on the `frame` timeline."""
    for t in range(video.shape[1]):
        rec.set_time("frame", sequence=t)
        rec.log(f"/{name}/{camera}/input", rr.Image(to_hwc_uint8(video[view, t])))
        rec.log(f"/{name}/{camera}/reconstruction", rr.Image(to_hwc_uint8(out.reconstruction[view, t])))
        log_token_map(rec, f"/{name}/{camera}/tokens", out.tokens[view, t], codebook)
        rec.log(f"/{name}/{camera}/psnr", rr.Scalars(float(out.psnr[view, t])))


def reconstruct(cfg: DictConfig, module: ImageTokenizerModule, run_dir: Path) -> dict[str, Any]:
    """Tokenize and reconstruct `num_clips` validation clips; write one mp4 per camera, tokens and a .rrd."""
    datamodule = instantiate(cfg.data)
    datamodule.setup("validate")
    clips = datamodule.val_clips
    pipeline = TokenizerReconstructionPipeline(module.tokenizer)
    rec = rr.RecordingStream("gaia_app", recording_id=f"generate-{run_dir.name}")
    rec.save(str(run_dir / "reconstruction.rrd"))
    results: dict[str, Any] = {}
    codebook = module.codebook_embeddings().detach().cpu()
    for i in tqdm(range(min(cfg.num_clips, len(clips))), desc="reconstruct"):
        clip = fit_to_resolution(clips[i], datamodule.height, datamodule.width, datamodule.resize_mode)
        video = to_float(torch.from_numpy(clip.frames))
        out = pipeline(video)
        names = [c.name for c in clip.cameras] if clip.cameras else clip.meta.get("camera_names", [f"view{v}" for v in range(clip.num_views)])
        for v, camera in enumerate(names):
            write_video(run_dir / f"{clip.clip_id}_{camera}.mp4", side_by_side(video[v], out.reconstruction[v]), clip.fps or 25.0)
            log_reconstruction(rec, clip.clip_id, camera, video, out, v, codebook)
        np.save(run_dir / f"{clip.clip_id}_tokens.npy", out.tokens.numpy())
        results[clip.clip_id] = {"psnr": float(out.psnr.mean()), "ssim": float(out.ssim.mean())}
    rec.flush()
    rec.disconnect()
    return results


MODES = {"reconstruct": (ImageTokenizerModule, reconstruct)}


def generate(cfg: DictConfig) -> dict[str, Any]:
    """Load `cfg.ckpt`, run `cfg.mode`, write results.json in the run dir and return the results."""
    L.seed_everything(cfg.seed, workers=True)
    run_dir = Path(cfg.paths.output_dir)
    save_resolved_config(cfg, run_dir)
    if cfg.mode not in MODES:
        raise ValueError(f"mode={cfg.mode}: expected one of {sorted(MODES)}")
    module_type, run = MODES[cfg.mode]
    module = load_module(cfg.ckpt, map_location=cfg.device)
    if not isinstance(module, module_type):
        raise TypeError(f"mode={cfg.mode} needs a {module_type.__name__} checkpoint; {cfg.ckpt} holds {type(module).__name__}")
    results = run(cfg, module, run_dir)
    atomic_write_text(run_dir / "results.json", json.dumps(results, indent=2))
    log.info("wrote mp4s, tokens, reconstruction.rrd and results.json to %s", run_dir)
    return {"results": results, "run_dir": run_dir}
