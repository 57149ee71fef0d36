"""No file can run code (issue: nothing runs, nothing lost): one test per attack on configs and checkpoints read
from files, each asserting the load is refused with the file named and that no marker file appears.

Attacks: an OmegaConf interpolation in a weights YAML (`${oc.create:{_target_: ...}}`, which passed the
`_target_` check on the unresolved text), in nested and top-level checkpoint hyper-parameters, `${oc.env:...}`,
a pickled entry in a sharded checkpoint's `.distcp`, a shard index naming files outside its folder, a YAML alias
bomb and a 50k-deep nested list.
"""

from __future__ import annotations

import pickle
import shutil
import time
from pathlib import Path

import pytest
import torch
import yaml

from gaia_app.lit.checkpoint import UnsafeCheckpointError, check_checkpoint_file, load_module, read_checkpoint
from gaia_app.tasks.generate import generate
from gaia_app.utils.untrusted import MAX_DEPTH, UntrustedDataError, check_plain, read_untrusted_yaml
from gaia_app.weights.folders import WEIGHTS_ROOT, load_nets
from gaia_app.weights.nets import checkpoint_nets
from tests.conftest import Payload, compose_config, tampered

pytestmark = pytest.mark.usefixtures("one_thread")


def creating(marker: Path) -> str:
    """An interpolation that, once resolved and instantiated, creates `marker`."""
    return "${oc.create:{_target_: pathlib.Path.touch, self: '" + str(marker) + "'}}"


def hostile_weights(tmp_path: Path, value: str, where=("nets", "net", "channels")) -> Path:
    """A copy of the shipped GAIA-1 weights whose tokenizer YAML holds `value` at `where`."""
    folder = tmp_path / "weights"
    shutil.copytree(WEIGHTS_ROOT / "gaia1", folder)
    path = folder / "tokenizer.yaml"
    config = yaml.safe_load(path.read_text())
    node = config
    for key in where[:-1]:
        node = node[key]
    node[where[-1]] = value
    path.write_text(yaml.safe_dump(config))
    return folder


@pytest.mark.parametrize("where", [("nets", "net", "channels"), ("nets", "net", "extra"), ("info", "image_size")])
def test_an_interpolation_in_a_weights_yaml_is_refused_and_runs_nothing(tmp_path: Path, where) -> None:
    marker = tmp_path / "pwned"
    folder = hostile_weights(tmp_path, creating(marker), where)
    with pytest.raises(ValueError, match=r"tokenizer\.yaml.*is an OmegaConf interpolation"):
        load_nets(folder, "tokenizer")
    cfg = compose_config("generate", ["mode=reconstruct", f"weights={folder}", "data=synthetic_frames_tiny",
                                      "num_clips=1", "extras.print_config=false"], tmp_path / "gen")
    with pytest.raises(ValueError, match="OmegaConf interpolation"):
        generate(cfg)
    assert not marker.exists()


def test_an_environment_interpolation_in_a_weights_yaml_is_refused(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("GAIA_SECRET_TOKEN", "hunter2")
    folder = hostile_weights(tmp_path, "${oc.env:GAIA_SECRET_TOKEN}", ("nets", "net", "extra"))
    with pytest.raises(ValueError, match=r"nets\.net\.extra: '\$\{oc\.env:GAIA_SECRET_TOKEN\}' is an OmegaConf"):
        load_nets(folder, "tokenizer")


@pytest.mark.parametrize("where", ["nested", "top_level", "model_cfg_key", "datamodule"])
def test_an_interpolation_in_checkpoint_hyper_parameters_is_refused(genuine: Path, tmp_path: Path, where) -> None:
    marker = tmp_path / "pwned"

    def edit(checkpoint: dict) -> None:
        hyper = checkpoint["hyper_parameters"]
        if where == "nested":  # a net argument, built by instantiate
            hyper["model_cfg"]["net"]["channels"] = creating(marker)
        elif where == "top_level":
            hyper["extra"] = creating(marker)
        elif where == "model_cfg_key":  # a key, not a value
            hyper["model_cfg"][creating(marker)] = 1
        else:
            checkpoint["datamodule_hyper_parameters"] = {"root": creating(marker)}

    path = tampered(genuine, tmp_path, edit)
    for load in (read_checkpoint, load_module, check_checkpoint_file,
                 lambda p: checkpoint_nets(p, "tokenizer", role="ckpt")):
        with pytest.raises(UntrustedDataError, match=rf"checkpoint '{path}'.*OmegaConf interpolation"):
            load(path)
    cfg = compose_config("generate", ["mode=reconstruct", f"ckpt={path}", "data=synthetic_frames_tiny",
                                      "num_clips=1", "extras.print_config=false"], tmp_path / "gen")
    with pytest.raises(UntrustedDataError):
        generate(cfg)
    assert not marker.exists()


def test_a_genuine_weights_folder_and_checkpoint_pass_the_checks(genuine: Path) -> None:
    for family in ("gaia1", "gaia2"):
        for yaml_file in (WEIGHTS_ROOT / family).glob("*.yaml"):
            read_untrusted_yaml(yaml_file)
    nets, _, _ = checkpoint_nets(genuine, "tokenizer", role="ckpt")
    assert set(nets) == {"net"}


# ---------------------------------------------------------------- YAML size, aliases, nesting

def test_a_yaml_alias_bomb_is_refused_quickly(tmp_path: Path) -> None:
    lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
    lines += [f"a{i}: &a{i} [*a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}, "
              f"*a{i - 1}, *a{i - 1}, *a{i - 1}]" for i in range(1, 9)]
    folder = hostile_weights(tmp_path, "placeholder")
    path = folder / "tokenizer.yaml"
    path.write_text("\n".join(lines) + "\n" + path.read_text())
    assert path.stat().st_size < 2048
    started = time.perf_counter()
    with pytest.raises(ValueError, match=r"tokenizer\.yaml: line 1: YAML anchors and aliases are refused"):
        load_nets(folder, "tokenizer")
    assert time.perf_counter() - started < 5  # the unbounded walk took > 60 s and 1.5 GB


@pytest.mark.parametrize("depth", [MAX_DEPTH + 1, 50_000])
def test_deeply_nested_yaml_is_refused_with_its_line(tmp_path: Path, depth: int) -> None:
    folder = hostile_weights(tmp_path, "placeholder")
    path = folder / "tokenizer.yaml"
    path.write_text(path.read_text() + "deep: " + "[" * depth + "]" * depth + "\n")
    with pytest.raises(ValueError, match=rf"nested more than {MAX_DEPTH} levels deep"):
        load_nets(folder, "tokenizer")


def test_an_oversized_yaml_is_refused_before_it_is_parsed(tmp_path: Path) -> None:
    path = tmp_path / "big.yaml"
    path.write_text("x: '" + "y" * (2 << 20) + "'\n")
    with pytest.raises(UntrustedDataError, match="2097158 bytes, more than the 1048576 a config file may have"):
        read_untrusted_yaml(path)


def test_deep_checkpoint_data_is_refused_without_recursion(genuine: Path, tmp_path: Path) -> None:
    deep: list = []
    node = deep
    for _ in range(50_000):
        node.append([])
        node = node[0]
    with pytest.raises(UntrustedDataError, match=r"hp\.x(\[0\])+: nested more than"):
        check_plain({"x": deep}, "hp")


# ---------------------------------------------------------------- sharded checkpoints

@pytest.fixture
def sharded(genuine: Path, tmp_path: Path):
    """A genuine sharded checkpoint folder (the tokenizer's weights in .distcp shards, Lightning's meta.pt beside
    them) and a function that writes a variant with `extra` entries in its shards."""
    import torch.distributed.checkpoint as dcp

    checkpoint = torch.load(genuine, weights_only=True)

    def make(name: str, extra: dict | None = None) -> Path:
        folder = tmp_path / name
        weights = {"state_dict": dict(checkpoint["state_dict"]), "optimizer": {"param_groups": [{"lr": 1e-3}]}}
        dcp.save({**weights, **(extra or {})}, checkpoint_id=folder, no_dist=True)
        meta = {k: v for k, v in checkpoint.items() if k not in ("state_dict", "optimizer_states")}
        torch.save(meta, folder / "meta.pt")
        return folder

    return make


@pytest.mark.filterwarnings("ignore:torch.distributed is disabled")
def test_a_genuine_sharded_checkpoint_loads_its_tensors(sharded, genuine: Path) -> None:
    folder = sharded("good.ckpt")
    check_checkpoint_file(folder)
    loaded = read_checkpoint(folder)["state_dict"]
    reference = torch.load(genuine, weights_only=True)["state_dict"]
    assert loaded.keys() == reference.keys()
    assert all(torch.equal(loaded[k], reference[k]) for k in reference)


@pytest.mark.filterwarnings("ignore:torch.distributed is disabled")
def test_a_pickled_shard_entry_is_refused_and_runs_nothing(sharded, tmp_path: Path) -> None:
    marker = tmp_path / "pwned"
    folder = sharded("evil.ckpt", {"extra": Payload(marker)})
    for load in (read_checkpoint, check_checkpoint_file):
        with pytest.raises(UnsafeCheckpointError, match=rf"'{folder}' was refused: shard entries .* 'extra'"):
            load(folder)
    assert not marker.exists()


@pytest.mark.filterwarnings("ignore:torch.distributed is disabled")
@pytest.mark.parametrize("escape", ["../outside/__0_0.distcp", "../../../../../../etc/passwd", "/etc/passwd"])
def test_a_shard_index_naming_files_outside_its_folder_is_refused(sharded, tmp_path: Path, escape: str) -> None:
    from gaia_app.weights.checkpoints import DcpMetadataUnpickler

    folder = sharded("escape.ckpt")
    outside = tmp_path / "outside"
    outside.mkdir()
    shutil.copy(folder / "__0_0.distcp", outside / "__0_0.distcp")
    with (folder / ".metadata").open("rb") as f:
        metadata = DcpMetadataUnpickler(f).load()
    for info in metadata.storage_data.values():
        info.relative_path = escape
    (folder / ".metadata").write_bytes(pickle.dumps(metadata))
    for load in (read_checkpoint, check_checkpoint_file):
        with pytest.raises(UnsafeCheckpointError, match=rf"names '{escape}', which is not a file inside"):
            load(folder)


def test_a_stored_decoder_sampler_is_built_only_from_the_diffusion_package(tmp_path: Path) -> None:
    from gaia_app.pipelines.gaia1 import decoder_sampling
    from gaia_app.weights.targets import UnsafeTargetError

    marker = tmp_path / "pwned"
    for sampler in ({"_target_": "gaia_app.diffusion.samplers.torch.save", "obj": 1, "f": str(marker)},
                    {"_target_": "gaia_app.diffusion.samplers.DDIMSampler", "_partial_": True,
                     "steps": creating(marker)}):
        with pytest.raises((UnsafeTargetError, UntrustedDataError), match="video decoder checkpoint's model config"):
            decoder_sampling({"sampler": sampler}, steps=None)
    assert not marker.exists()


@pytest.mark.parametrize("path", ["agent_raster", "action_raster"])
def test_a_conditioning_path_the_net_does_not_have_is_refused_by_its_key(tmp_path: Path, path: str) -> None:
    """Issue 50: a GAIA-1 world-model YAML asking for one of GAIA-2's rasters names the key, not a TypeError."""
    folder = tmp_path / "gaia1"
    shutil.copytree(WEIGHTS_ROOT / "gaia1", folder)
    config_path = folder / "world_model.yaml"
    config = yaml.safe_load(config_path.read_text())
    config["nets"]["net"][path] = True
    config_path.write_text(yaml.safe_dump(config))
    with pytest.raises(ValueError, match=rf"world_model\.yaml: nets\.net\.{path}: WorldModel has no argument '{path}'"):
        load_nets(folder, "world_model")
