"""Every config file composes, resolves, and instantiates its data/model/trainer on tiny settings."""

from __future__ import annotations

from pathlib import Path

import lightning as L
import pytest
from hydra.utils import instantiate
from omegaconf import OmegaConf

from gaia_app.lit.base import GaiaModule
from tests.conftest import CLIP_PROJECTION, CONF_DIR, compose_config

GROUPS = ["data", "model", "model/net", "model/optim", "model/sched", "trainer", "debug", "logger", "callbacks",
          "paths", "extras", "hydra"]
EXPERIMENTS = sorted(str(p.relative_to(CONF_DIR / "experiment").with_suffix(""))
                     for p in (CONF_DIR / "experiment").rglob("*.yaml"))


def shrink(experiment: str, clip_dir: Path | None = None) -> list[str]:
    """What keeps instantiation cheap for an experiment: its family's tiny net and a CPU trainer; the local CLIP
    of GAIA-2's paper run is the tiny test CLIP in `clip_dir`."""
    if experiment.startswith("gaia2/"):
        net = "gaia2_world_model_tiny" if "world_model" in experiment else "gaia2_video_tokenizer_tiny"
        clip = ([f"model.text_encoder.path={clip_dir}", f"model.text_encoder.dim={CLIP_PROJECTION}"]
                if experiment.endswith("world_model_paper") else [])
        return [f"model/net={net}", "trainer=tiny", *clip]
    family = next((f for f in ("world_model", "video_decoder") if f in experiment), "tokenizer")
    family = "world_model" if experiment.endswith("scaling") else family  # a sweep over world-model sizes
    net = f"gaia1_{family}_tiny"
    # the paper's T5-large is a local directory a user provides (the trainable keyword encoder stands in)
    text = (["model/text_encoder=learned", "~model.text_encoder.path"] if experiment.endswith("world_model_paper")
            else [])
    return [f"model/net={net}", "trainer=tiny", *text]


def options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))


def resolve_job(cfg) -> dict:
    job = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
    return OmegaConf.to_container(job, resolve=True, throw_on_missing=True)


@pytest.fixture(scope="module")
def clip_root(tmp_path_factory) -> Path:
    """Two exported synthetic clips in the clip-folder format, for the video_folder data options."""
    from gaia_app.data.clip_writer import write_clip
    from gaia_app.data.synthetic import generate_clip

    root = tmp_path_factory.mktemp("clips")
    for seed in (1, 2):
        write_clip(generate_clip(seed=seed, height=64, width=112, cameras=["front"], clip_len=16, fps=25.0), root)
    return root


def data_overrides(option: str, clip_root: Path) -> list[str]:
    if option.startswith("video_folder") and not option.endswith("_shards"):
        return [f"data.source.root={clip_root}"]
    if option == "commavq" and not (CONF_DIR.parent.parent / "shared" / "data" / "commavq" / "tokens.npy").exists():
        pytest.skip("commavq tokens absent (../shared/data)")
    return []


@pytest.mark.parametrize("group,option", [(g, o) for g in GROUPS for o in options(g)])
def test_every_option_composes_and_resolves(group: str, option: str, tmp_path: Path, clip_root: Path) -> None:
    extra = data_overrides(option, clip_root) if group == "data" else []
    cfg = compose_config("train", [f"{group}={option}", *extra], tmp_path)
    resolve_job(cfg)


@pytest.mark.parametrize("option", options("data"))
def test_every_data_option_instantiates(option: str, tmp_path: Path, clip_root: Path) -> None:
    cfg = compose_config("train", [f"data={option}", *data_overrides(option, clip_root)], tmp_path)
    dm = instantiate(cfg.data)
    assert isinstance(dm, L.LightningDataModule)


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_every_experiment_instantiates(experiment: str, tmp_path: Path, clip_root: Path, tiny_clip_dir: Path) -> None:
    cfg = compose_config("train", [f"experiment={experiment}", *shrink(experiment, tiny_clip_dir)], tmp_path)
    if cfg.data.get("source", {}).get("_target_", "").endswith("ClipFolderDataset"):
        cfg.data.source.root = str(clip_root)
        cfg.data.source.min_frames = min(cfg.data.source.min_frames, 16)  # the test clips have 16 frames
    resolve_job(cfg)
    from gaia_app.tasks.train import build

    objects = build(cfg)
    assert isinstance(objects["model"], GaiaModule) and isinstance(objects["trainer"], L.Trainer)
    objects["model"].configure_model()
    assert sum(p.numel() for p in objects["model"].parameters()) > 0


@pytest.mark.parametrize("guidance", options("guidance"))
def test_generate_config_composes(guidance: str, tmp_path: Path) -> None:
    from hydra.utils import instantiate

    cfg = compose_config("generate", ["ckpt=some.ckpt", f"guidance={guidance}"], tmp_path)
    assert resolve_job(cfg)["mode"] == "reconstruct"
    assert instantiate(cfg.guidance).scales(3, 4).shape == (3, 4)
    assert instantiate(cfg.token_sampler).picker.mode == "top_k"


@pytest.mark.parametrize("family", ["gaia1", "gaia2"])
def test_generate_families_compose(family: str, tmp_path: Path) -> None:
    """generate.py model=gaia1|gaia2: the GAIA-2 family instantiates the report's solver (Euler, 50 linear-quadratic
    steps) and guidance switched off by default."""
    from hydra.utils import instantiate

    cfg = compose_config("generate", [f"model={family}", "data=synthetic_rig"], tmp_path)
    assert resolve_job(cfg)["model"]["family"] == family
    if family == "gaia2":
        sampler, guidance = instantiate(cfg.model.sampler), instantiate(cfg.model.guidance)
        assert (sampler.steps, sampler.schedule, sampler.solver) == (50, "linear_quadratic", "euler")
        assert not guidance.active and list(guidance.conditions) == ["agents"]


@pytest.mark.parametrize("mode", options("mode"))
def test_every_generation_mode_has_one_registry_entry_and_its_settings_beside_it(mode: str, tmp_path: Path) -> None:
    """conf/mode/<name>.yaml and the registry (gaia_app/tasks/modes.py) name the same modes; selecting a mode sets
    `mode` and brings its own settings, and only its own (showcase / controllability / evaluate sections)."""
    from gaia_app.tasks.modes import MODES

    family = "gaia2" if mode in ("scratch", "rollout", "inpaint", "edit") else "gaia1"
    cfg = resolve_job(compose_config("generate", [f"model={family}", f"mode={mode}"], tmp_path))
    assert cfg["mode"] == mode and mode in MODES and family in MODES[mode].runs
    own = {"showcase": "showcase", "evaluate": "evaluate", "reconstruct": "num_clips", "export": "export_dtype"}
    for name, key in own.items():
        assert (key in cfg) == (name == mode), (mode, key)
    assert ("probe_clips" in cfg["controllability"]) == (mode == "controllability")


def test_the_registry_lists_exactly_the_mode_configs() -> None:
    from gaia_app.tasks.modes import MODES

    assert sorted(MODES) == options("mode")


def test_an_unknown_mode_names_the_modes_there_are(tmp_path: Path) -> None:
    from hydra.errors import MissingConfigException

    from gaia_app.tasks.modes import mode_run

    with pytest.raises(MissingConfigException, match=r"(?s)mode/fly.*showcase"):
        compose_config("generate", ["mode=fly"], tmp_path)
    with pytest.raises(ValueError, match=r"model=gaia2 mode=video: expected one of \['evaluate', 'export', 'scratch'"):
        mode_run("gaia2", "video")


def test_experiment_values_win_over_root_defaults(tmp_path: Path) -> None:
    cfg = compose_config("train", ["experiment=gaia1/tokenizer_tiny"], tmp_path)
    assert cfg.run_name == "gaia1_tokenizer_tiny" and cfg.trainer.max_steps == 1200
