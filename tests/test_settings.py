"""Every setting checked where it enters (issue: nothing runs, nothing lost): a table of (setting, bad value,
expected message fragment), each failing at once with one line naming the setting, the value and the range."""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path

import pytest
from omegaconf import OmegaConf, open_dict

from gaia_app.tasks.generate import generate
from gaia_app.tasks.settings import GENERATE_RULES, TRAIN_RULES, SettingError, check_settings
from gaia_app.tasks.train import train
from tests.conftest import CONF_DIR, TINY_TOKENIZER, compose_config

pytestmark = pytest.mark.usefixtures("one_thread")

GENERATE_TABLE = [
    ("num_futures", 100000, "num_futures=100000: expected an integer in [1, 64]"),
    ("num_futures", 0, "num_futures=0: expected an integer in [1, 64]"),
    ("seconds", 1e6, "seconds=1000000.0: expected a finite number in (0, 120]"),
    ("seconds", math.nan, "seconds=nan: expected a finite number"),
    ("token_sampler.picker.temperature", math.nan,
     "token_sampler.picker.temperature=nan: expected a finite number in (0"),
    ("token_sampler.picker.temperature", 0, "token_sampler.picker.temperature=0: expected a finite number in (0"),
    ("guidance.scale", -1, "guidance.scale=-1: expected a finite number in [0, 100]"),
    ("guidance.scale", math.nan, "guidance.scale=nan: expected a finite number in [0, 100]"),
    ("seed", -1, "seed=-1: expected an integer in [0, 4294967295]"),
    ("seed", 2**70, "seed=1180591620717411303424: expected an integer in [0, 4294967295]"),
    ("prompt", 123, "prompt=123: expected a text of at most 2000 characters"),
    ("prompt", "x" * 100_000, "prompt=<100000 characters>: expected a text of at most 2000 characters"),
    ("fps", math.nan, "fps=nan: expected a finite number in (0, 1000]"),
    ("rate", 0, "rate=0: expected a finite number in (0, 100]"),
    ("decoder_steps", 0, "decoder_steps=0: expected an integer in [1, 1000]"),
    ("max_clips", 0, "max_clips=0: expected an integer in [1, ∞]"),
    ("max_clips", -1, "max_clips=-1: expected an integer in [1, ∞]"),
    ("num_clips", 0, "num_clips=0: expected an integer in [1, ∞]"),
    ("num_clips", -1, "num_clips=-1: expected an integer in [1, ∞]"),
    ("context.index", -1, "context.index=-1: expected an integer in [0, ∞]"),
    ("context.index", 1.7, "context.index=1.7: expected an integer in [0, ∞]"),
    ("workers", -2, "workers=-2: expected an integer in [0, 256]"),
]


@pytest.mark.parametrize(("setting", "value", "message"), GENERATE_TABLE, ids=[f"{s}={str(v)[:12]}" for s, v, _ in
                                                                              GENERATE_TABLE])
def test_generate_refuses_each_bad_setting_where_it_enters(setting: str, value, message: str, tmp_path: Path) -> None:
    cfg = compose_config("generate", ["mode=action", "weights=gaia1", "extras.print_config=false"], tmp_path)
    with open_dict(cfg):
        OmegaConf.update(cfg, setting, value, force_add=True)
    with pytest.raises(SettingError) as error:
        generate(cfg)
    assert message in str(error.value) and "\n" not in str(error.value)
    assert not (tmp_path / "results.json").exists()


@pytest.mark.parametrize(("setting", "value", "message"), [
    ("model.optim.lr", "abc", "model.optim.lr='abc': expected a finite number in (0, 10]"),
    ("model.optim.lr", -1e-3, "model.optim.lr=-0.001: expected a finite number in (0, 10]"),
    ("seed", -1, "seed=-1: expected an integer in [0, 4294967295]"),
    ("trainer.max_steps", 1.5, "trainer.max_steps=1.5: expected an integer in [-1, ∞]"),
])
def test_train_refuses_each_bad_setting_where_it_enters(setting: str, value, message: str, tmp_path: Path) -> None:
    cfg = compose_config("train", TINY_TOKENIZER, tmp_path)
    with open_dict(cfg):
        OmegaConf.update(cfg, setting, value, force_add=True)
    with pytest.raises(SettingError, match=message.replace("(", r"\(").replace("[", r"\[").replace("]", r"\]")):
        train(cfg)


def test_every_shipped_config_passes_its_rules(tmp_path: Path) -> None:
    """The rules must never refuse a configuration the project itself ships."""
    for experiment in sorted((CONF_DIR / "experiment").rglob("*.yaml")):
        name = experiment.relative_to(CONF_DIR / "experiment").with_suffix("").as_posix()
        check_settings(compose_config("train", [f"experiment={name}"], tmp_path), TRAIN_RULES)
    for overrides in ([], ["model=gaia2"], ["guidance=scheduled"], ["mode=showcase", "weights=gaia1"]):
        check_settings(compose_config("generate", overrides, tmp_path), GENERATE_RULES)


def test_a_rate_the_weights_would_ignore_is_refused(tmp_path: Path) -> None:
    cfg = compose_config("generate", ["mode=action", "weights=gaia1", "speed=brake", "rate=5",
                                      "extras.print_config=false"], tmp_path)
    with pytest.raises(ValueError, match=r"rate=5: weights=gaia1 runs its world model at 6\.25 Hz"):
        generate(cfg)


def test_a_prompt_the_text_encoder_would_cut_is_refused(tmp_path: Path) -> None:
    prompt = "It is night. It is snowing. It is raining. It is foggy. We turn left."
    cfg = compose_config("generate", ["mode=text", "weights=gaia1", f"prompt='{prompt}'", "extras.print_config=false"],
                         tmp_path)
    with pytest.raises(ValueError, match=r"prompt: 6 keywords, but the world model's text encoder reads 4"):
        generate(cfg)


# ---------------------------------------------------------------- settings in files and other entry points

def test_a_non_finite_fps_in_meta_json_is_refused(tmp_path: Path) -> None:
    from gaia_app.data.clip import ClipError
    from gaia_app.data.clip_folder import read_clip
    from gaia_app.data.clip_writer import write_clip
    from gaia_app.data.synthetic import generate_clip

    folder = write_clip(generate_clip(seed=0, height=32, width=56, clip_len=4), tmp_path)
    meta = json.loads((folder / "meta.json").read_text())
    for bad in ("NaN", "Infinity"):
        (folder / "meta.json").write_text(json.dumps(meta).replace(f'"fps": {meta["fps"]}', f'"fps": {bad}'))
        with pytest.raises(ClipError, match=r"meta\.json: field 'fps' must be a positive finite number, got (nan|inf)"):
            read_clip(folder)


def test_a_symlink_leaving_a_clip_folder_is_refused(tmp_path: Path) -> None:
    from gaia_app.data.clip import ClipError
    from gaia_app.data.clip_folder import read_clip
    from gaia_app.data.clip_writer import write_clip
    from gaia_app.data.shard import folder_files
    from gaia_app.data.synthetic import generate_clip

    folder = write_clip(generate_clip(seed=0, height=32, width=56, clip_len=4), tmp_path / "clips")
    secret = tmp_path / "secret.txt"
    secret.write_text("not for the shard")
    os.symlink(secret, folder / "notes.txt")
    for read in (read_clip, folder_files):
        with pytest.raises(ClipError, match=r"notes\.txt: a symbolic link to .*secret\.txt, outside its clip folder"):
            read(folder)
    (folder / "notes.txt").unlink()
    os.symlink(folder / "labels.jsonl", folder / "labels_copy.jsonl")  # a link inside the folder stays allowed
    read_clip(folder)


@pytest.mark.parametrize(("option", "value", "message"), [
    ("clip_len_s", 0, "--clip-seconds 0: expected a positive finite number"),
    ("clip_len_s", math.inf, "--clip-seconds inf: expected a positive finite number"),
    ("fps", -5.0, "--fps -5.0: expected a positive finite number"),
    ("max_gap", 0.0, "--max-gap 0.0: expected a positive finite number"),
])
def test_dashcam_options_are_checked_before_reading(option: str, value, message: str, tmp_path: Path) -> None:
    from gaia_app.data.importers.dashcam import import_dashcam

    with pytest.raises(ValueError, match=message.replace("(", r"\(")):
        import_dashcam(tmp_path / "never_opened.mp4", tmp_path / "clips", **{option: value}, progress=False)


@pytest.mark.parametrize("speed", [1e9, 1e39])
def test_telemetry_outside_the_label_range_names_its_record(speed: float, tmp_path: Path) -> None:
    import numpy as np

    from gaia_app.data.clip import ClipError
    from gaia_app.data.importers.telemetry import actions_at, read_telemetry

    path = tmp_path / "log.csv"
    path.write_text("t,speed,curvature\n0,10,0\n0.5," + repr(speed) + ",0\n1,10,0\n")
    with pytest.raises(ClipError, match=re.escape(f"log.csv: record 2 gives speed {speed:g}, outside [-100, 100] m/s")):
        actions_at(read_telemetry(path), np.array([0.0, 0.4, 0.8]))


@pytest.mark.parametrize("port", [0, 99999, -1, "abc"])
def test_viewer_ports_are_checked(port) -> None:
    from gaia_app.viz.viewer import port_open, viewer_args

    for call in (lambda: viewer_args(port), lambda: port_open("127.0.0.1", port)):
        with pytest.raises(ValueError, match=rf"viewer port {port!r}: expected a TCP port number in \[1, 65535\]"):
            call()
