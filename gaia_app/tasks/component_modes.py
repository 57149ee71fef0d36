"""The single-tokenizer modes of `generate.py`: reconstruct (mp4s, tokens, metrics and a .rrd; a GAIA-2 video
tokenizer: mp4s and PSNR / SSIM per camera), tokenize (a token cache for the GAIA-1 world model) and encode (a GAIA-2
latent cache with every condition beside the latents), on the tokenizer of `ckpt=` or of `weights=`."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig
from tqdm import tqdm

from gaia_app.data.cache_manifest import cache_manifest, prepare_cache, weights_sha256
from gaia_app.data.datasets import fit_to_resolution
from gaia_app.data.latent_cache import clip_done, write_latent_clip
from gaia_app.data.names import inside
from gaia_app.data.token_cache import segment_done, write_segment
from gaia_app.data.transforms import to_float, to_uint8
from gaia_app.data.video_io import write_video
from gaia_app.eval.metrics import psnr, ssim
from gaia_app.models.gaia2.video_tokenizer import VideoTokenizer
from gaia_app.models.tokenizer_protocol import DiscreteTokenizer
from gaia_app.pipelines.gaia1_tokenizer import (
    ReconstructionOutput,
    TokenCachePipeline,
    TokenizerReconstructionPipeline,
    camera_names,
    segment_names,
)
from gaia_app.pipelines.gaia2_video_tokenizer import VideoTokenizerPipeline
from gaia_app.utils.locks import folder_lock
from gaia_app.viz.media import log_token_map, to_hwc_uint8
from gaia_app.weights.folders import load_nets, shipped_folder
from gaia_app.weights.nets import checkpoint_nets


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


def reconstruct(cfg: DictConfig, tokenizer: DiscreteTokenizer, run_dir: Path) -> dict[str, Any]:
    """Tokenize and reconstruct `num_clips` validation clips; write one mp4 per camera, tokens and a .rrd."""
    datamodule = instantiate(cfg.data)
    datamodule.setup("validate")
    clips = datamodule.val_clips
    pipeline = TokenizerReconstructionPipeline(tokenizer)
    rec = rr.RecordingStream("gaia_app", recording_id=f"generate-{run_dir.name}")
    rec.save(str(run_dir / "reconstruction.rrd"))
    results: dict[str, Any] = {}
    codebook = tokenizer.code_vectors().cpu()
    for i in tqdm(range(min(cfg.num_clips, len(clips))), desc="reconstruct"):
        clip = fit_to_resolution(clips[i], datamodule.height, datamodule.width, datamodule.resize_mode)
        video = to_float(torch.from_numpy(clip.frames))
        out = pipeline(video)
        for v, camera in enumerate(camera_names(clip)):
            write_video(inside(run_dir, f"{clip.clip_id}_{camera}.mp4"), side_by_side(video[v], out.reconstruction[v]),
                        clip.fps or 25.0)
            log_reconstruction(rec, clip.clip_id, camera, video, out, v, codebook)
        np.save(inside(run_dir, f"{clip.clip_id}_tokens.npy"), out.tokens.numpy())
        results[clip.clip_id] = {"psnr": float(out.psnr.mean()), "ssim": float(out.ssim.mean())}
    rec.flush()
    rec.disconnect()
    return results


def reconstruct_video(cfg: DictConfig, tokenizer: VideoTokenizer, run_dir: Path) -> dict[str, Any]:
    """A GAIA-2 video tokenizer on `num_clips` validation clips: per clip and camera the PSNR and SSIM of the
    reconstruction (posterior mean decoded, whole latent steps) and an mp4 (input | reconstruction)."""
    datamodule = instantiate(cfg.data)
    datamodule.setup("validate")
    clips = datamodule.val_clips
    pipeline = VideoTokenizerPipeline(tokenizer, datamodule.height, datamodule.width, datamodule.resize_mode, cfg.fps)
    results: dict[str, Any] = {}
    for i in tqdm(range(min(cfg.num_clips, len(clips))), desc="reconstruct"):
        clip = clips[i]
        with torch.no_grad():
            out = pipeline.reconstruct(clip)
        video, reconstruction = out.video.cpu(), out.reconstruction.cpu()  # (v, T, 3, H, W)
        per_camera = {}
        for v, camera in enumerate(camera_names(clip)):
            write_video(inside(run_dir, f"{clip.clip_id}_{camera}.mp4"), side_by_side(video[v], reconstruction[v]),
                        cfg.fps or clip.fps or 25.0)
            per_camera[camera] = {"psnr": float(psnr(reconstruction[v], video[v]).mean()),
                                  "ssim": float(ssim(reconstruction[v], video[v]).mean())}
        results[clip.clip_id] = per_camera
    return results


def cache_split(clips: Any, out_dir: Path, max_clips: int | None, desc: str, done: Callable[[Any], bool],
                write: Callable[[Any], None], workers: int = 0) -> dict[str, int]:
    """Write the clips of one split with `write(clip)`; clips for which `done(clip)` holds are skipped (resumable:
    each cache writes its marker file last and atomically). `workers` > 0 reads (renders, decodes) the clips in that
    many background processes, in order, while this one encodes and writes."""
    counts = {"written": 0, "skipped": 0}
    n = len(clips) if max_clips is None else min(max_clips, len(clips))
    for clip in tqdm(read_in_order(clips, n, workers), total=n, desc=desc):
        if done(clip):
            counts["skipped"] += 1
            continue
        write(clip)
        counts["written"] += 1
    return counts


def read_in_order(clips: Any, n: int, workers: int) -> Any:
    """The first `n` clips of `clips`, read here (workers=0) or by a DataLoader's worker processes, in order."""
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
        raise ValueError(f"workers: expected a non-negative integer, got {workers!r}")
    if workers == 0:
        return (clips[i] for i in range(n))
    subset = torch.utils.data.Subset(clips, range(n))
    # batch_size=None with an identity collate hands each clip over untouched; the loader keeps the index order
    return torch.utils.data.DataLoader(subset, batch_size=None, num_workers=workers, prefetch_factor=4,
                                       collate_fn=as_read)


def as_read(clip: Any) -> Any:
    """A DataLoader collate that changes nothing (module-level, so worker processes can pickle it)."""
    return clip


def cache_splits(cfg: DictConfig, name: str, make_writers: Callable[[Any, Path], tuple[Callable, Callable]],
                 manifest: Callable[[Any], dict[str, Any]]) -> dict[str, Any]:
    """Run `cache_split` over `cfg.splits` of `cfg.data` into `cfg.out_dir/<split>/`; make_writers(datamodule,
    out_dir) → (done, write). Each split folder must hold no cache, or one with the same manifest(datamodule)
    (data/cache_manifest.py; `cfg.overwrite` empties a folder that holds another)."""
    datamodule = instantiate(cfg.data)
    datamodule.setup("fit")
    made = manifest(datamodule)
    splits = {"train": datamodule.train_clips, "val": datamodule.val_clips}
    results: dict[str, Any] = {}
    for split in cfg.splits:
        if split not in splits:
            raise ValueError(f"splits: unknown split '{split}', expected some of {sorted(splits)}")
        out_dir = Path(cfg.out_dir) / split
        with folder_lock(out_dir, "out_dir"):  # one writer per cache folder, from the manifest check to the end
            prepare_cache(out_dir, made, overwrite=bool(cfg.overwrite))
            done, write = make_writers(datamodule, out_dir)
            results[split] = {**cache_split(splits[split], out_dir, cfg.max_clips, f"{name} {split}", done, write,
                                            cfg.workers),
                              "out_dir": str(out_dir)}
    return results


def tokenize(cfg: DictConfig, tokenizer: DiscreteTokenizer, run_dir: Path) -> dict[str, Any]:
    """Encode every clip of `cfg.splits` once into `cfg.out_dir/<split>/` (token_cache.py layout),
    with timestamps, actions and captions beside the tokens (GAIA-1 §2.2: the world model trains on tokens)."""
    def writers(datamodule: Any, out_dir: Path) -> tuple[Callable, Callable]:
        pipeline = TokenCachePipeline(tokenizer, datamodule.height, datamodule.width, datamodule.resize_mode,
                                      cfg.fps, cfg.batch_size)

        def write(clip: Any) -> None:
            for segment in pipeline(clip).segments:
                write_segment(out_dir, segment)

        return (lambda clip: all(segment_done(out_dir, name) for name in segment_names(clip))), write

    def manifest(datamodule: Any) -> dict[str, Any]:
        return cache_manifest("gaia1_tokens", tokenizer_sha256=weights_sha256(tokenizer),
                              codebook_size=tokenizer.codebook_size, fps=cfg.fps,
                              image_size=[datamodule.height, datamodule.width], resize_mode=datamodule.resize_mode)

    return cache_splits(cfg, "tokenize", writers, manifest)


def encode(cfg: DictConfig, tokenizer: VideoTokenizer, run_dir: Path) -> dict[str, Any]:
    """Encode every multi-camera clip of `cfg.splits` once into `cfg.out_dir/<split>/` (latent_cache.py layout):
    GAIA-2 tokenizer latents with every condition beside them, for the latent world model (GAIA-2 report, tokenizer)."""
    def writers(datamodule: Any, out_dir: Path) -> tuple[Callable, Callable]:
        pipeline = VideoTokenizerPipeline(tokenizer, datamodule.height, datamodule.width,
                                          datamodule.resize_mode, cfg.fps)
        return ((lambda clip: clip_done(out_dir, clip.clip_id)),
                (lambda clip: write_latent_clip(out_dir, pipeline.encode(clip))))

    def manifest(datamodule: Any) -> dict[str, Any]:
        return cache_manifest("gaia2_latents", tokenizer_sha256=weights_sha256(tokenizer), fps=cfg.fps,
                              image_size=[datamodule.height, datamodule.width], resize_mode=datamodule.resize_mode)

    return cache_splits(cfg, "encode", writers, manifest)


# mode → {the checkpoint component it runs on: the run}
COMPONENT_RUNS = {"reconstruct": {"tokenizer": reconstruct, "video_tokenizer": reconstruct_video},
                  "tokenize": {"tokenizer": tokenize}, "encode": {"video_tokenizer": encode}}


def run_component(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """mode=reconstruct / tokenize / encode on the tokenizer net of `cfg.ckpt` (built from the checkpoint's tensors and
    checked config, weights/nets.py), or on the tokenizer of `cfg.weights`."""
    if cfg.mode in ("tokenize", "reconstruct") and cfg.get("weights"):
        return COMPONENT_RUNS[cfg.mode]["tokenizer"](cfg, shipped_tokenizer(cfg), run_dir)
    if cfg.mode == "encode" and cfg.get("weights"):
        return encode(cfg, shipped_tokenizer(cfg, "video_tokenizer"), run_dir)
    if not cfg.ckpt:
        raise ValueError(f"mode={cfg.mode} needs ckpt=<checkpoint of a trained tokenizer>")
    runs = COMPONENT_RUNS[cfg.mode]
    try:
        loaded = checkpoint_nets(cfg.ckpt, tuple(runs), "ckpt", cfg.device)
    except TypeError as error:
        raise TypeError(f"mode={cfg.mode}: {error}") from None
    return runs[loaded.component](cfg, loaded.nets["net"], run_dir)


def shipped_tokenizer(cfg: DictConfig, component: str = "tokenizer") -> DiscreteTokenizer | VideoTokenizer:
    """The image tokenizer (or GAIA-2 video tokenizer) of the weights folder `cfg.weights` (e.g. gaia1, gaia2), checked
    against the data's frame size: a token or latent cache for a world model that will run beside those weights
    (or be fine-tuned from them, model.init_from)."""
    if cfg.ckpt:
        raise ValueError(f"weights={cfg.weights} replaces ckpt={cfg.ckpt}; give one of them")
    nets, info = load_nets(shipped_folder(cfg.weights), component, cfg.device)
    size = tuple(info.get("image_size", ()))
    if size != (cfg.data.height, cfg.data.width):
        raise ValueError(f"weights={cfg.weights}: its tokenizer was trained on {size} frames, but data.height × "
                         f"data.width is {(cfg.data.height, cfg.data.width)}; set them to match")
    return nets["net"]
