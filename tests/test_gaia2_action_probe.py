"""The GAIA-2 action table's probe, trained once, saved and loaded by later runs (protocols/gaia2_action_probe.py)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
import yaml
from hydra import compose, initialize_config_dir

from gaia_app.protocols import gaia2_action_probe
from gaia_app.protocols.gaia2_action_probe import INFO, WEIGHTS, action_probe, load_action_probe

CONF = Path(__file__).resolve().parents[1] / "conf"
FRAMES = 8
TINY = ["model=gaia2", "data=synthetic_rig", "context.seed=5", "model.evaluate.probe_clips=2",
        "model.evaluate.probe_steps=2"]


def rig_config(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("generate", overrides=[*TINY, *overrides])


@pytest.fixture(scope="module")
def saved(tmp_path_factory) -> tuple[Path, torch.nn.Module, dict]:
    folder = tmp_path_factory.mktemp("probe") / "action_probe"
    probe, info = action_probe(rig_config(), FRAMES, save_to=folder)
    return folder, probe, info


def test_a_trained_probe_is_saved_and_a_later_run_loads_it_instead_of_training(saved, monkeypatch) -> None:
    folder, trained, info = saved
    assert (folder / WEIGHTS).is_file() and info["probe_seed"] == 4343 and "fit" in info
    monkeypatch.setattr(gaia2_action_probe, "train_action_probe", lambda *a: pytest.fail("trained a second probe"))
    loaded, loaded_info = action_probe(rig_config(f"model.evaluate.action_probe={folder}"), FRAMES)
    assert loaded_info["loaded_from"] == str(folder) and loaded_info["fit"] == info["fit"]
    pair = torch.rand(2, 2, 3, 3, 64, 112, generator=torch.Generator().manual_seed(0))  # (b, 2 frames, 3 cameras, …)
    with torch.no_grad():
        torch.testing.assert_close(loaded(pair), trained.eval()(pair))


@pytest.mark.parametrize(("override", "named"), [("model.evaluate.probe_stride=1", "probe_stride=2"),
                                                 ("model.evaluate.probe_cameras=front", "probe_cameras='rig'"),
                                                 ("data.source.height=32", "image_size=\\[64, 112\\]"),
                                                 ("context.seed=4343", "trained on world 4343")])
def test_a_probe_that_reads_other_pictures_is_refused_naming_the_setting(saved, override, named) -> None:
    folder, _, _ = saved
    with pytest.raises(ValueError, match=named):
        load_action_probe(folder, rig_config(override), FRAMES)


def test_a_missing_or_unreadable_probe_file_is_named(saved, tmp_path) -> None:
    folder, _, _ = saved
    with pytest.raises(FileNotFoundError, match=WEIGHTS):
        load_action_probe(tmp_path, rig_config(), FRAMES)
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / INFO).write_text((folder / INFO).read_text())
    (broken / WEIGHTS).write_bytes(b"not a tensor file")
    with pytest.raises(ValueError, match="not a readable safetensors file"):
        load_action_probe(broken, rig_config(), FRAMES)
    info = yaml.safe_load((folder / INFO).read_text())
    assert info["cameras"] == ["front", "front_left", "front_right"] and info["rate"] == 12.5
