"""OmegaConf resolvers used by the configs; registered once on import."""

from __future__ import annotations

import os

from omegaconf import OmegaConf

VAL_SEED_OFFSET = 1_000_003


def launch_id(default: str) -> str:
    """The name every rank of one launch agrees on, for the run dir (docs/distributed.md).

    Under `srun` the SLURM job and step ids; under torchrun its rendezvous id (`--standalone` draws one, multi-node
    launches pass `--rdzv-id`); otherwise `default` (a timestamp: a single process, or Lightning's own DDP launch,
    which hands its run dir to the processes it starts).
    """
    job, step = os.environ.get("SLURM_JOB_ID"), os.environ.get("SLURM_STEP_ID")
    if job and step:
        return f"slurm{job}.{step}"
    rendezvous = os.environ.get("TORCHELASTIC_RUN_ID")
    if rendezvous and rendezvous != "none":
        return f"torchrun_{rendezvous}"
    return default


def register_resolvers() -> None:
    # a different, fixed seed for validation worlds: the same clip never appears in train and val
    OmegaConf.register_new_resolver("val_seed", lambda seed: int(seed) + VAL_SEED_OFFSET, replace=True)
    # ranks started by srun / torchrun compose their configs separately: a timestamp alone could differ
    OmegaConf.register_new_resolver("launch_id", launch_id, replace=True)
    # this process's id: default run dirs of two runs started in the same second differ (cached: one value per run)
    OmegaConf.register_new_resolver("pid", lambda: str(os.getpid()), use_cache=True, replace=True)


register_resolvers()
