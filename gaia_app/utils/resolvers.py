"""OmegaConf resolvers used by the configs; registered once on import."""

from __future__ import annotations

from omegaconf import OmegaConf

VAL_SEED_OFFSET = 1_000_003


def register_resolvers() -> None:
    # a different, fixed seed for validation worlds: the same clip never appears in train and val
    OmegaConf.register_new_resolver("val_seed", lambda seed: int(seed) + VAL_SEED_OFFSET, replace=True)


register_resolvers()
