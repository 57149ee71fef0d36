"""What the checks of files from elsewhere cost at load time, side by side in one run (docs/benchmarks.md, "Safe
loading"): the checked path of gaia_app against the unchecked reads it replaced.

- weights YAMLs: `read_untrusted_yaml` (size, event scan for aliases and depth, plain-data walk) vs `yaml.safe_load`;
- shipped nets: `load_nets` (checked YAML, `instantiate_checked`, finite tensors) vs `yaml.safe_load` +
  `instantiate` + `load_state_dict`, for every component of gaia_app/weights;
- a training checkpoint: `read_checkpoint` (weights-only load, hyper-parameters walked) vs `torch.load(weights_only)`;
- a sharded checkpoint folder: `read_checkpoint` (safe index, paths inside, tensors through the safe planner) vs
  torch's `dcp_to_torch_save` + `torch.load`.
Medians of `--repeats` alternating runs.

    python benchmarks/bench_safe_loading.py --repeats 5
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import torch
import yaml
from hydra.utils import instantiate

from gaia_app.utils.untrusted import read_untrusted_yaml
from gaia_app.weights.checkpoints import read_checkpoint
from gaia_app.weights.folders import WEIGHTS_ROOT, load_nets

COMPONENTS = [("gaia1", "tokenizer"), ("gaia1", "world_model"), ("gaia1", "video_decoder"),
              ("gaia2", "video_tokenizer"), ("gaia2", "latent_world_model")]


def unchecked_nets(folder: Path, component: str) -> dict[str, torch.nn.Module]:
    """The load without checks: YAML, instantiate, tensors."""
    from safetensors.torch import load_file

    config = yaml.safe_load((folder / f"{component}.yaml").read_text())
    state = load_file(str(folder / f"{component}.safetensors"))
    nets = {}
    for key, net_config in config["nets"].items():
        made = instantiate(net_config)
        net = made() if callable(made) and not isinstance(made, torch.nn.Module) else made
        net.load_state_dict({n[len(key) + 1:]: v for n, v in state.items() if n.startswith(f"{key}.")})
        nets[key] = net
    return nets


def checkpoint_files(folder: Path) -> tuple[Path, Path]:
    """A single-file checkpoint of the shipped GAIA-1 world model's tensors (with a plain model config) and the same
    tensors as a sharded folder."""
    import torch.distributed.checkpoint as dcp
    from safetensors.torch import load_file

    state = {f"net.{k}": v.float()
             for k, v in load_file(str(WEIGHTS_ROOT / "gaia1" / "world_model.safetensors")).items()}
    config = yaml.safe_load((WEIGHTS_ROOT / "gaia1" / "world_model.yaml").read_text())
    checkpoint = {"state_dict": state, "hyper_parameters": {"model_cfg": {"net": config["nets"]["net"]}},
                  "epoch": 0, "global_step": 0}
    single = folder / "world_model.ckpt"
    torch.save(checkpoint, single)
    sharded = folder / "sharded.ckpt"
    dcp.save({"state_dict": state}, checkpoint_id=sharded, no_dist=True)
    torch.save({k: v for k, v in checkpoint.items() if k != "state_dict"}, sharded / "meta.pt")
    return single, sharded


def unchecked_sharded(folder: Path) -> dict:
    from torch.distributed.checkpoint.format_utils import dcp_to_torch_save

    with tempfile.TemporaryDirectory() as tmp:
        dcp_to_torch_save(folder, Path(tmp) / "all.pt")
        return torch.load(Path(tmp) / "all.pt", weights_only=True)


def timed(pairs: dict[str, tuple[Callable[[], object], Callable[[], object]]], repeats: int) -> None:
    for name, (checked, unchecked) in pairs.items():
        seconds: dict[str, list[float]] = {"checked": [], "unchecked": []}
        for _ in range(repeats):
            for label, load in (("checked", checked), ("unchecked", unchecked)):
                start = time.perf_counter()
                load()
                seconds[label].append(time.perf_counter() - start)
        a, b = statistics.median(seconds["checked"]), statistics.median(seconds["unchecked"])
        print(f"| {name} | {a * 1e3:.1f} | {b * 1e3:.1f} | {a / b:.2f}× |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"medians of {args.repeats}, one thread\n\n"
          "| load | checked (ms) | unchecked (ms) | ratio |\n|---|---:|---:|---:|")
    pairs: dict[str, tuple[Callable[[], object], Callable[[], object]]] = {}
    for family, component in COMPONENTS:
        path = WEIGHTS_ROOT / family / f"{component}.yaml"
        pairs[f"{family}/{component}.yaml"] = (lambda p=path: read_untrusted_yaml(p),
                                               lambda p=path: yaml.safe_load(p.read_text()))
    for family, component in COMPONENTS:
        folder = WEIGHTS_ROOT / family
        pairs[f"{family} {component} nets"] = (lambda f=folder, c=component: load_nets(f, c),
                                              lambda f=folder, c=component: unchecked_nets(f, c))
    with tempfile.TemporaryDirectory() as tmp:
        single, sharded = checkpoint_files(Path(tmp))
        pairs["checkpoint file (GAIA-1 world model)"] = (lambda: read_checkpoint(single),
                                                          lambda: torch.load(single, weights_only=True))
        pairs["sharded checkpoint folder (same tensors)"] = (lambda: read_checkpoint(sharded),
                                                             lambda: unchecked_sharded(sharded))
        timed(pairs, args.repeats)


if __name__ == "__main__":
    import warnings

    warnings.filterwarnings("ignore", message="torch.distributed is disabled")
    main()
