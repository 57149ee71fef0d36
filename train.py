"""Train a gaia_app component: `python train.py experiment=gaia1/tokenizer_tiny` (see README)."""

import hydra
from omegaconf import DictConfig

import gaia_app.utils.resolvers  # noqa: F401  (registers ${val_seed:...})
from gaia_app.tasks.common import prepare


@hydra.main(version_base="1.3", config_path="conf", config_name="train")
def main(cfg: DictConfig) -> None:
    from gaia_app.tasks.train import train

    prepare(cfg)
    train(cfg)


if __name__ == "__main__":
    main()
