"""Start-of-run setup shared by train and generate."""

from __future__ import annotations

import logging

from omegaconf import DictConfig, OmegaConf

from gaia_app.utils.threads import apply_thread_policy

log = logging.getLogger(__name__)


def prepare(cfg: DictConfig) -> None:
    """Apply `extras`: the thread count (gaia_app/utils/threads.py: extras.num_threads, else OMP_NUM_THREADS, else
    the CPUs allowed less those other processes keep busy) and an optional print of the composed job config."""
    extras = cfg.get("extras") or {}
    threads, why = apply_thread_policy(extras.get("num_threads"))
    log.info("CPU threads: %d (%s); extras.num_threads sets another count", threads, why)
    if extras.get("print_config"):
        job = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
        log.info("config:\n%s", OmegaConf.to_yaml(job))
