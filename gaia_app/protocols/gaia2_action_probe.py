"""The GAIA-2 action table's inverse-dynamics probe, trained once and reused (protocols/gaia2_actions.py).

Training the rig probe takes about half of an action table's time on a CPU (1 500 steps on 96 clips: 30 of 67
minutes), and it depends on neither the weights nor the scenes scored. `model.evaluate.action_probe=<folder>` loads
the probe a run saved (`<run dir>/action_probe`, or `--out`/action_probe of benchmarks/gaia2_action_adherence.py)
instead of training it; the folder holds `action_probe.safetensors` (weights only) and `action_probe.yaml` (what it
was trained on). A probe is reused only where it reads the same thing: the same rig, image size, rate, cameras read
and frame stride, trained on a world other than the one scored.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml
from omegaconf import DictConfig
from torch import nn

from gaia_app.data.synthetic.rig import resolve_camera_names
from gaia_app.models.probes import InverseDynamicsProbe
from gaia_app.protocols.gaia2_actions import probe_stride, probe_views, train_action_probe
from gaia_app.utils.run_dir import atomic_write_bytes, atomic_write_text

WEIGHTS, INFO = "action_probe.safetensors", "action_probe.yaml"
# what a saved probe must share with the run that loads it: otherwise it reads other pictures
MUST_MATCH = ("cameras", "probe_cameras", "image_size", "rate", "probe_stride")


def probe_info(cfg: DictConfig, frames: int) -> dict[str, Any]:
    """What `train_action_probe(cfg, frames)` trains on and reads: the rig's cameras, image size (H, W) and rate, the
    cameras the probe reads, its frame stride, and the probe world's settings."""
    e, source = cfg.model.evaluate, cfg.data.source
    return {"cameras": resolve_camera_names(source.cameras), "probe_cameras": str(e.probe_cameras),
            "image_size": [int(source.height), int(source.width)], "rate": float(source.fps),
            "probe_stride": probe_stride(cfg), "frames": int(frames), "probe_seed": int(e.probe_seed),
            "probe_clips": int(e.probe_clips), "probe_steps": int(e.probe_steps),
            "probe_driven_share": float(e.probe_driven_share), "seed": int(cfg.seed)}


def save_action_probe(folder: str | Path, probe: nn.Module, info: dict[str, Any],
                      files: tuple[str, str] = (WEIGHTS, INFO)) -> None:
    """Write `probe` (weights only) and `info` (probe_info plus its fit) into `folder` as files (weights, info), each
    atomically; the twin probe (protocols/gaia2_twin_probe.py) is saved the same way under its own names."""
    from safetensors.torch import save as save_tensors

    folder = Path(folder)
    state = {key: value.contiguous() for key, value in probe.state_dict().items()}
    atomic_write_bytes(folder / files[0], save_tensors(state))
    atomic_write_text(folder / files[1], yaml.safe_dump(info, sort_keys=False))


def load_action_probe(folder: str | Path, cfg: DictConfig, frames: int) -> tuple[InverseDynamicsProbe, dict[str, Any]]:
    """The probe saved in `folder` and its info; FileNotFoundError or ValueError naming the file and the setting that
    does not fit this run (MUST_MATCH, or a probe trained on the world this run scores)."""
    views = probe_views(cfg)
    probe = InverseDynamicsProbe(cameras=len(views) if views else 1)
    saved = load_saved_probe(probe, Path(folder), (WEIGHTS, INFO), "action_probe", probe_info(cfg, frames),
                             MUST_MATCH, int(cfg.context.seed))
    return probe.eval(), saved


def load_saved_probe(probe: nn.Module, folder: Path, files: tuple[str, str], setting: str, wanted: dict[str, Any],
                     must_match: tuple[str, ...], scored_world: int) -> dict[str, Any]:
    """Load into `probe` the weights saved in `folder` as files (weights, info) by a run whose probe_info is
    `wanted`, and return that info: FileNotFoundError naming `model.evaluate.<setting>` and the missing file,
    ValueError naming the file and the setting of `must_match` that differs, the world when the probe was trained on
    `scored_world`, or weights this version's probe cannot take."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    weights, info = (folder / name for name in files)
    for path in (weights, info):
        if not path.is_file():
            raise FileNotFoundError(f"model.evaluate.{setting}={folder}: {path.name} is missing (leave it null to "
                                    f"train the probe; a run saves it as {setting}/)")
    saved = yaml.safe_load(info.read_text()) or {}
    for key in must_match:
        if saved.get(key) != wanted[key]:
            raise ValueError(f"{info}: the probe was trained for {key}={saved.get(key)!r}, this run needs "
                             f"{wanted[key]!r}")
    if saved.get("probe_seed") == scored_world:
        raise ValueError(f"{info}: the probe was trained on world {saved['probe_seed']}, the world this run "
                         f"scores (context.seed); use a probe of another world")
    try:
        state = load_file(str(weights))
    except (SafetensorError, OSError) as error:
        raise ValueError(f"{weights}: not a readable safetensors file ({error})") from error
    try:
        probe.load_state_dict(state)
    except RuntimeError as error:
        raise ValueError(f"{weights}: does not match this version's {setting.replace('_', ' ')} ({error})") from error
    return saved


def action_probe(cfg: DictConfig, frames: int,
                 save_to: str | Path | None = None) -> tuple[InverseDynamicsProbe, dict[str, Any]]:
    """The action probe and its info (with "fit" and "loaded_from" where it was loaded): `model.evaluate.action_probe`
    loaded, or trained and, with `save_to`, saved there for later runs."""
    folder = cfg.model.evaluate.get("action_probe")
    if folder:
        probe, info = load_action_probe(folder, cfg, frames)
        return probe, {**info, "loaded_from": str(folder)}
    probe, fit = train_action_probe(cfg, frames)
    info = {**probe_info(cfg, frames), "fit": fit}
    if save_to is not None:
        save_action_probe(save_to, probe, info)
    return probe, info
