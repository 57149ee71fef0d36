"""`generate.py mode=export`: a shipped-weights folder (gaia_app/pipelines/shipped.py) from training checkpoints.

    python generate.py mode=export tokenizer_ckpt=<tokenizer last.ckpt> world_model_ckpt=<world model last.ckpt> \\
        controllability.probes=<probes folder> out_dir=gaia_app/weights/gaia1

writes tokenizer.{safetensors,yaml}, world_model.{safetensors,yaml} and probes/ (the controllability probes the
weights were measured with, so `weights=` runs never retrain them). Only the nets inference needs are kept: the
tokenizer without its discriminator, the world model with its text encoder.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from gaia_app.eval.controllability import PROBE_INFO, PROBE_WEIGHTS, load_probes
from gaia_app.lit.checkpoint import read_checkpoint
from gaia_app.pipelines.shipped import export_component


def export(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Export `cfg.tokenizer_ckpt`, `cfg.world_model_ckpt` and `cfg.controllability.probes` into `cfg.out_dir`."""
    for key in ("tokenizer_ckpt", "world_model_ckpt"):
        if not cfg.get(key):
            raise ValueError(f"mode=export needs {key}=<checkpoint>")
    image_size = [int(cfg.data.height), int(cfg.data.width)]
    out = Path(cfg.out_dir)
    results = {"out_dir": str(out)}
    tokenizer = read_checkpoint(cfg.tokenizer_ckpt)
    results["tokenizer"] = export_component(tokenizer, out, "tokenizer", ["net"],
                                            {"image_size": image_size},
                                            cfg.export_dtype)
    world_model = read_checkpoint(cfg.world_model_ckpt)
    nets = ["net"] + (["text_encoder"] if world_model["hyper_parameters"]["model_cfg"].get("text_encoder") else [])
    results["world_model"] = export_component(world_model, out, "world_model", nets,
                                              {"rate": float(cfg.rate)},
                                              cfg.export_dtype)
    if cfg.controllability.probes:
        load_probes(cfg.controllability.probes, tuple(image_size), float(cfg.rate))  # refuses probes of another size
        (out / "probes").mkdir(parents=True, exist_ok=True)
        for name in (PROBE_WEIGHTS, PROBE_INFO):
            shutil.copyfile(Path(cfg.controllability.probes) / name, out / "probes" / name)
        results["probes"] = str(out / "probes")
    return results
