"""`train(cfg)`: build data, model, callbacks, loggers and trainer from the config and fit."""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

import lightning as L
from hydra.core.hydra_config import HydraConfig
from hydra.errors import InstantiationException
from hydra.types import RunMode
from hydra.utils import instantiate
from lightning.pytorch.utilities import rank_zero_only
from omegaconf import DictConfig, OmegaConf

from gaia_app.lit.compile import CompileNet
from gaia_app.lit.staged_checkpoints import recover_checkpoint
from gaia_app.lit.strategies import build_strategy
from gaia_app.tasks.settings import TRAIN_RULES, check_settings
from gaia_app.utils.run_dir import save_resolved_config
from gaia_app.viz.rerun_logger import rerun_logger_of
from gaia_app.weights.checkpoints import check_checkpoint_file

log = logging.getLogger(__name__)


def instantiate_list(node: DictConfig | None) -> list[Any]:
    """Instantiate every entry of a dict of `_target_` nodes (callbacks, loggers); null entries are skipped."""
    if not node:
        return []
    return [instantiate(v) for v in node.values() if v is not None and "_target_" in v]


def resume_path(ckpt_path: str | None, run_dir: Path) -> str | None:
    """`ckpt_path=last` resumes from this run dir's last.ckpt if present (and says so when it starts fresh); a
    path must exist. The checkpoint is checked to load safely (weights only, weights/checkpoints.py) before Lightning
    reads it."""
    if ckpt_path in (None, ""):
        return None
    if ckpt_path == "last":
        recover_checkpoint(run_dir / "checkpoints" / "last.ckpt")  # a sharded save interrupted mid-swap
        last = newest_last(run_dir / "checkpoints")
        if not last.exists():
            log.info("ckpt_path=last: no checkpoint in %s yet, so this run starts fresh from step 0", last.parent)
            return None
        ckpt_path = str(last)
    elif not recover_checkpoint(ckpt_path).exists():
        raise FileNotFoundError(f"ckpt_path={ckpt_path}: no such checkpoint")
    check_checkpoint_file(ckpt_path)
    return ckpt_path


def newest_last(checkpoints: Path) -> Path:
    """checkpoints/last.ckpt, or the newer last-v<N>.ckpt that Lightning's version counter wrote beside it in run
    dirs from before conf/callbacks/model_checkpoint.yaml switched the counter off (a warning names it)."""
    last = checkpoints / "last.ckpt"
    versions = sorted(checkpoints.glob("last-v*.ckpt"), key=lambda p: p.stat().st_mtime)
    if versions and (not last.exists() or versions[-1].stat().st_mtime > last.stat().st_mtime):
        log.warning("ckpt_path=last: %s is newer than last.ckpt; resuming from it", versions[-1].name)
        return versions[-1]
    return last


def build(cfg: DictConfig) -> dict[str, Any]:
    """Instantiate datamodule, model, callbacks, loggers and trainer (no fitting)."""
    if "family" in cfg.model:
        raise ValueError(f"model={cfg.model.family} is a generation family of generate.py, not a trainable model: "
                         "train with experiment=gaia1/... or experiment=gaia2/...")
    datamodule = instantiate_setting(cfg.data, "data")
    model = instantiate_setting(cfg.model, "model")
    # the model's own config travels in the checkpoint so generate.py can rebuild it without Hydra
    model.save_hyperparameters({"model_cfg": OmegaConf.to_container(cfg.model, resolve=True)})
    callbacks = instantiate_list(cfg.get("callbacks"))
    if cfg.get("compile") and cfg.compile.enabled:
        callbacks.append(CompileNet(backend=cfg.compile.backend, mode=cfg.compile.mode, dynamic=cfg.compile.dynamic))
    loggers = instantiate_list(cfg.get("logger"))
    trainer_cfg = OmegaConf.to_container(cfg.trainer, resolve=True)
    trainer_cfg.pop("strategy", None)  # type: ignore[union-attr]  (built from the model's blocks below)
    strategy = build_strategy(cfg.trainer.get("strategy"), model)
    trainer: L.Trainer = instantiate(trainer_cfg, callbacks=callbacks, logger=loggers or False, strategy=strategy)
    check_sweep_launch(trainer)
    return {"datamodule": datamodule, "model": model, "trainer": trainer}


def instantiate_setting(node: DictConfig, name: str) -> Any:
    """instantiate(node), with a one-line error naming the setting when a key is not an argument of its target
    (e.g. experiment=gaia1/video_decoder_tiny sets data.source.clip_len, a setting of the synthetic world, and
    data=video_folder swaps in a clip-folder source that has none)."""
    try:
        return instantiate(node)
    except InstantiationException as error:
        found = re.search(r"Error in call to target '([^']+)':\s*TypeError\(.*unexpected keyword argument '(\w+)'",
                          str(error), re.S)
        key = re.search(r"full_key: (\S+)", str(error))
        if not found:
            raise
        where = key.group(1) if key else name  # Hydra's full key already starts at the root
        raise ValueError(f"{where}.{found.group(2)}: {found.group(1)} takes no '{found.group(2)}' (a setting meant "
                         f"for another {name} config); remove it with ~{where}.{found.group(2)}") from None


def check_sweep_launch(trainer: L.Trainer) -> None:
    """Refuse `-m` sweeps with a strategy that re-launches train.py per rank: each child would re-run the sweep."""
    if not (HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN):
        return
    launcher = getattr(trainer.strategy, "launcher", None)
    if launcher is not None and type(launcher).__name__ == "_SubprocessScriptLauncher":
        raise ValueError(
            f"hydra -m sweep with {type(trainer.strategy).__name__} on {trainer.num_devices} devices: Lightning would "
            "re-launch train.py with the sweep's arguments on every rank, so each rank re-runs the whole sweep. Sweep "
            "through the submitit launcher with srun (one task per device), or run single jobs (docs/distributed.md)")


def train(cfg: DictConfig) -> dict[str, Any]:
    """Seed, save the resolved config, fit (optionally resuming), validate; return metrics and objects."""
    check_settings(cfg, TRAIN_RULES)
    L.seed_everything(cfg.seed, workers=True)
    run_dir = Path(cfg.paths.output_dir)
    rank_zero_only(save_resolved_config)(cfg, run_dir)  # other ranks share the run dir (Lightning / torchrun)
    objects = build(cfg)
    trainer, model, datamodule = objects["trainer"], objects["model"], objects["datamodule"]
    if (recording := rerun_logger_of(trainer)) is not None:
        recording.log_config(OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"]))
    ckpt = resume_path(cfg.get("ckpt_path"), run_dir)
    if ckpt:
        log.info("resuming from %s", ckpt)
    # weights_only: Lightning's own resume load must not unpickle code either
    trainer.fit(model, datamodule=datamodule, ckpt_path=ckpt, weights_only=True)
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items()}
    log.info("trained to step %d; run dir: %s", trainer.global_step, run_dir)
    return {"metrics": metrics, "run_dir": run_dir, **objects}
