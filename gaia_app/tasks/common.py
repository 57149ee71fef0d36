"""Start-of-run setup shared by train and generate."""

from __future__ import annotations

import logging

import torch
from omegaconf import DictConfig, OmegaConf

log = logging.getLogger(__name__)


def prepare(cfg: DictConfig) -> None:
    """Apply `extras`: thread count and an optional print of the composed job config."""
    extras = cfg.get("extras") or {}
    if extras.get("num_threads"):
        torch.set_num_threads(int(extras.num_threads))
    if extras.get("print_config"):
        job = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
        log.info("config:\n%s", OmegaConf.to_yaml(job))
