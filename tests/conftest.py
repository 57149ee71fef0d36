"""Shared fixtures: the config directory, a Hydra compose helper, and the optional real data."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, open_dict

import gaia_app.utils.resolvers  # noqa: F401

ROOT = Path(__file__).resolve().parents[1]
CONF_DIR = ROOT / "conf"
SHARED_DATA = ROOT.parent / "shared" / "data"

os.environ.setdefault("RERUN", "on")
torch.set_num_threads(2)


def compose_config(config_name: str, overrides: list[str], output_dir: Path) -> DictConfig:
    """Compose like @hydra.main does, with hydra.runtime.output_dir set so ${hydra:...} resolves."""
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name=config_name, overrides=overrides, return_hydra_config=True)
    with open_dict(cfg):
        cfg.hydra.runtime.output_dir = str(output_dir)
        cfg.hydra.job.name = "test"
        cfg.paths.root_dir = str(ROOT)
    HydraConfig().set_config(cfg)
    return cfg


@pytest.fixture
def shared_data() -> Path:
    """../shared/data beside the project; tests using it skip cleanly when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} is absent")
    return SHARED_DATA


@pytest.fixture(scope="module")
def one_thread():
    """For modules of tiny nets: OpenMP barriers between 2 threads cost more than they save, and far more
    when another process keeps a core busy. Use with `pytestmark = pytest.mark.usefixtures("one_thread")`."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
