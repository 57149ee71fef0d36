"""Run a trained gaia_app checkpoint: `python generate.py ckpt=outputs/.../last.ckpt` (see README)."""

import hydra
from omegaconf import DictConfig

import gaia_app.utils.resolvers  # noqa: F401  (registers ${val_seed:...})
from gaia_app.tasks.common import prepare


@hydra.main(version_base="1.3", config_path="conf", config_name="generate")
def main(cfg: DictConfig) -> None:
    from gaia_app.tasks.generate import generate

    prepare(cfg)
    generate(cfg)


if __name__ == "__main__":
    main()
