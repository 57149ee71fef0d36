"""`generate.py mode=export`: a shipped-weights folder (gaia_app/weights/folders.py) from training checkpoints.

    python generate.py mode=export tokenizer_ckpt=<tokenizer last.ckpt> world_model_ckpt=<world model last.ckpt> \\
        controllability.probes=<probes folder> out_dir=gaia_app/weights/gaia1

writes tokenizer.{safetensors,yaml}, world_model.{safetensors,yaml} and probes/ (the controllability probes the
weights were measured with, so `weights=` runs never retrain them); with decoder_ckpt= also
video_decoder.{safetensors,yaml} (its EMA weights), which `weights=` runs then decode with. Only the nets inference
needs are kept: the tokenizer without its discriminator, the world model with its text encoder.

    python generate.py mode=export weights=gaia1 world_model_ckpt=<world model last.ckpt> out_dir=my_weights

exports a world model trained on the tokens of a weights folder's tokenizer (`mode=tokenize weights=gaia1`): the
tokenizer files (and the probes, unless controllability.probes is given) are copied from that folder unchanged.

    python generate.py model=gaia2 mode=export tokenizer_ckpt=<video tokenizer last.ckpt> \
        world_model_ckpt=<latent world model last.ckpt> data=synthetic_rig out_dir=my_gaia2_weights

writes a GAIA-2 folder: video_tokenizer.{safetensors,yaml} (the tokenizer without its discriminator; info: the
input size data.height × data.width) and latent_world_model.{safetensors,yaml} (with its caption encoder; info: the
latent scale), which `model=gaia2 weights=<folder>` runs generate with.

    python generate.py [model=gaia2] mode=export export_parts=tokenizer tokenizer_ckpt=<last.ckpt> out_dir=<folder>

writes the tokenizer alone (tokenizer.* or video_tokenizer.*): a folder that `mode=tokenize` / `mode=encode
weights=<folder>` and benchmarks/agent_fidelity.py read, so a tokenizer trained on one machine can be tokenized with
and scored on another before any world model exists for it.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from gaia_app.eval.controllability import PROBE_INFO, PROBE_WEIGHTS, load_probes
from gaia_app.weights.checkpoints import read_checkpoint
from gaia_app.weights.folders import export_component, read_config, shipped_folder, weight_files
from gaia_app.weights.nets import checkpoint_component, held_by


def export_sources(cfg: DictConfig, mode: str, tokenizer: str, tokenizer_hint: str,
                   world_model_hint: str) -> Path | None:
    """The weights folder `cfg.weights` that gives the tokenizer (None without one), after checking that exactly
    one of it and `cfg.tokenizer_ckpt` is set, and that `cfg.world_model_ckpt` is; errors name `mode` and the key."""
    source = shipped_folder(cfg.weights) if cfg.get("weights") else None
    if source is not None and cfg.get("tokenizer_ckpt"):
        raise ValueError(f"{mode}: weights={cfg.weights} gives the {tokenizer}; drop tokenizer_ckpt")
    if not cfg.get("tokenizer_ckpt") and source is None:
        raise ValueError(f"{mode} needs tokenizer_ckpt={tokenizer_hint} (or weights=<folder> for the {tokenizer})")
    if not cfg.get("world_model_ckpt"):
        raise ValueError(f"{mode} needs world_model_ckpt={world_model_hint}")
    return source


EXPORT_PARTS = ("all", "tokenizer")


def tokenizer_only(cfg: DictConfig, component: str) -> dict[str, Any] | None:
    """With `export_parts=tokenizer`: `cfg.tokenizer_ckpt`'s `component` ("tokenizer" or "video_tokenizer") written
    alone into `cfg.out_dir` → the export's results; None for `export_parts=all`."""
    parts = cfg.get("export_parts", "all")
    if parts not in EXPORT_PARTS:
        raise ValueError(f"export_parts={parts!r}: expected one of {list(EXPORT_PARTS)}")
    if parts == "all":
        return None
    if not cfg.get("tokenizer_ckpt"):
        raise ValueError(f"mode=export export_parts=tokenizer needs tokenizer_ckpt=<checkpoint of a {component}>")
    for key in ("weights", "world_model_ckpt", "decoder_ckpt"):
        if cfg.get(key):
            raise ValueError(f"mode=export export_parts=tokenizer writes the tokenizer alone; drop {key}")
    checkpoint = checked_checkpoint(cfg.tokenizer_ckpt, "tokenizer_ckpt", component)
    out = Path(cfg.out_dir)
    return {"out_dir": str(out),
            component: export_component(checkpoint, out, component, ["net"],
                                        {"image_size": [int(cfg.data.height), int(cfg.data.width)]},
                                        cfg.export_dtype)}


def export(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Export `cfg.tokenizer_ckpt`, `cfg.world_model_ckpt` and `cfg.controllability.probes` into `cfg.out_dir`."""
    alone = tokenizer_only(cfg, "tokenizer")
    if alone is not None:
        return alone
    source = export_sources(cfg, "mode=export", "tokenizer", "<checkpoint>", "<checkpoint>")
    out = Path(cfg.out_dir)
    results: dict[str, Any] = {"out_dir": str(out)}
    if source is None:
        image_size = [int(cfg.data.height), int(cfg.data.width)]
        results["tokenizer"] = export_component(read_checkpoint(cfg.tokenizer_ckpt), out, "tokenizer", ["net"],
                                                {"image_size": image_size}, cfg.export_dtype)
    else:
        image_size = [int(v) for v in read_config(weight_files(source, "tokenizer")[1])["info"]["image_size"]]
        results["tokenizer"] = copy_component(source, out, "tokenizer")
    world_model = read_checkpoint(cfg.world_model_ckpt)
    nets = ["net"] + (["text_encoder"] if world_model["hyper_parameters"]["model_cfg"].get("text_encoder") else [])
    results["world_model"] = export_component(world_model, out, "world_model", nets,
                                              {"rate": float(cfg.rate)},
                                              cfg.export_dtype)
    if cfg.get("decoder_ckpt"):
        results["video_decoder"] = export_decoder(read_checkpoint(cfg.decoder_ckpt), out, cfg.export_dtype,
                                                  cfg.get("decoder_sampler"), cfg.get("decoder_steps"))
    probes = cfg.controllability.probes or (source / "probes" if source is not None else None)
    if probes:
        load_probes(probes, tuple(image_size), float(cfg.rate))  # refuses probes of another size
        (out / "probes").mkdir(parents=True, exist_ok=True)
        for name in (PROBE_WEIGHTS, PROBE_INFO):
            shutil.copyfile(Path(probes) / name, out / "probes" / name)
        results["probes"] = str(out / "probes")
    return results


def copy_component(source: Path, out: Path, component: str) -> str:
    """Copy `<component>.{safetensors,yaml}` of the weights folder `source` into `out` (nothing to do when they are
    the same folder): a folder exported from a new world model keeps the tokenizer it was trained on."""
    read_config(weight_files(source, component)[1])  # refuses a missing or foreign config
    out.mkdir(parents=True, exist_ok=True)
    for path in weight_files(source, component):
        if path.resolve() != (out / path.name).resolve():
            shutil.copyfile(path, out / path.name)
    return f"copied from {source}"


def checked_checkpoint(path: str, role: str, component: str) -> dict[str, Any]:
    """The checkpoint dict of `path` (read weights-only), refused with a message naming `role` unless it holds a
    `component` (e.g. "video_tokenizer", by the record the checkpoint carries, weights/nets.py)."""
    checkpoint = read_checkpoint(path)
    if checkpoint_component(checkpoint, path) != component:
        raise TypeError(f"{role}={path} holds a {held_by(checkpoint, path)} checkpoint, expected a {component} "
                        "checkpoint")
    return checkpoint


def export_gaia2(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """A GAIA-2 weights folder in `cfg.out_dir` from `cfg.tokenizer_ckpt` (or the video tokenizer of the weights
    folder `cfg.weights`, copied: a world model fine-tuned from shipped weights keeps their tokenizer) and
    `cfg.world_model_ckpt`."""
    alone = tokenizer_only(cfg, "video_tokenizer")
    if alone is not None:
        return alone
    source = export_sources(cfg, "model=gaia2 mode=export", "video tokenizer",
                            "<checkpoint of a GAIA-2 video tokenizer>", "<checkpoint of a GAIA-2 latent world model>")
    out = Path(cfg.out_dir)
    world_model = checked_checkpoint(cfg.world_model_ckpt, "world_model_ckpt", "latent_world_model")
    if source is None:
        tokenizer = checked_checkpoint(cfg.tokenizer_ckpt, "tokenizer_ckpt", "video_tokenizer")
        tokenizer_result: Any = export_component(tokenizer, out, "video_tokenizer", ["net"],
                                                 {"image_size": [int(cfg.data.height), int(cfg.data.width)]},
                                                 cfg.export_dtype)
    else:
        tokenizer_result = copy_component(source, out, "video_tokenizer")
    model_cfg = world_model["hyper_parameters"]["model_cfg"]
    nets = ["net"] + (["text_encoder"] if model_cfg.get("text_encoder") else [])
    return {"out_dir": str(out), "video_tokenizer": tokenizer_result,
            "latent_world_model": export_component(world_model, out, "latent_world_model", nets,
                                                   {"latent_scale": float(model_cfg.get("latent_scale", 1.0))},
                                                   cfg.export_dtype)}


def export_decoder(checkpoint: dict[str, Any], out: Path, dtype: str, sampler: str | None = None,
                   steps: int | None = None) -> dict[str, Any]:
    """video_decoder.{safetensors,yaml} from a video decoder checkpoint: its EMA weights (what generation samples
    with, GAIA-1 §4.3) and, as info, what the decoding pipeline needs (T', context frames, diffusion timesteps) and
    the decoding setting `weights=` runs default to: `sampler` ("ddim" or "one_step_mean") and `steps`, else the
    run's own sampler (DDIM) and steps."""
    from gaia_app.pipelines.gaia1 import DECODER_SAMPLERS

    if sampler is not None and sampler not in DECODER_SAMPLERS:
        raise ValueError(f"decoder_sampler: expected one of {DECODER_SAMPLERS}, got {sampler!r}")
    model_cfg = checkpoint["hyper_parameters"]["model_cfg"]
    if not str(model_cfg.get("_target_", "")).endswith("VideoDecoderModule"):
        raise ValueError(f"decoder_ckpt holds a {model_cfg.get('_target_')} checkpoint, expected a VideoDecoderModule")
    info = {"frames": int(model_cfg["frames"]), "context_frames": int(model_cfg["context_frames"]),
            "timesteps": int(model_cfg["schedule"].get("timesteps", 1000)), "sampler": sampler or "ddim",
            "steps": int(steps or model_cfg["sampler"]["steps"])}
    return export_component(checkpoint, out, "video_decoder", ["net"], info, dtype, prefixes={"net": "ema.module."})
