"""Every `generate.py` mode in one registry: its name, the model families it runs on, and what it does.

A mode's settings live beside it in `conf/mode/<name>.yaml` (a `# @package _global_` file that also sets
`mode: <name>`), so `mode=<name>` on the command line selects both; settings shared by several modes (checkpoints,
context, sampler, decoder) stay in `conf/generate.yaml`. tests/test_configs.py checks that the registry and the
config group name the same modes. A new mode is one entry here and one file there.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from gaia_app.pipelines.gaia1_inputs import MODES as ROLLOUT_CONDITIONS
from gaia_app.pipelines.gaia2 import GAIA2_MODES
from gaia_app.protocols.controllability import controllability
from gaia_app.protocols.evaluate import evaluate
from gaia_app.protocols.gaia2_evaluate import gaia2_evaluate
from gaia_app.tasks.component_modes import run_component
from gaia_app.tasks.export import export, export_gaia2
from gaia_app.tasks.gaia2_generate import gaia2_generate
from gaia_app.tasks.rollout import rollout
from gaia_app.tasks.showcase import showcase

Run = Callable[[DictConfig, Path], dict[str, Any]]


@dataclass(frozen=True)
class Mode:
    """One `generate.py` mode: `runs` maps each model family it runs on (`model=gaia1|gaia2`) to its run."""

    name: str
    summary: str
    runs: dict[str, Run]


ROLLOUT_SUMMARIES = {
    "video": "continue a context clip, no condition",
    "action": "continue a context clip under commanded speed= / curvature=",
    "text": "continue a context clip under prompt=",
    "text_action": "continue a context clip under prompt= and speed= / curvature=",
    "text_only": "generate from prompt= alone, no video",
    "unconditional": "generate from nothing",
}
GAIA2_SUMMARIES = {
    "scratch": "GAIA-2: model.steps latent steps from noise under the clip's conditions",
    "rollout": "GAIA-2: a clean context, then model.chunks chunks of new steps",
    "inpaint": "GAIA-2: regenerate a region of the clip (model.inpaint), keep the rest",
    "edit": "GAIA-2: noise the clip's latents and denoise them under edited conditions",
}


def _registry() -> dict[str, Mode]:
    modes = [
        Mode("reconstruct", "a tokenizer's reconstructions of validation clips (mp4s, tokens, metrics, .rrd)",
             {"gaia1": run_component}),
        Mode("tokenize", "a token cache of whole splits for the GAIA-1 world model", {"gaia1": run_component}),
        Mode("encode", "a GAIA-2 latent cache of whole multi-camera splits (a video tokenizer ckpt= or weights=)",
             {"gaia1": run_component}),
        *(Mode(name, ROLLOUT_SUMMARIES[name], {"gaia1": rollout}) for name in ROLLOUT_CONDITIONS),
        Mode("controllability", "action / text adherence of rollouts read by probes, with ceiling and floor",
             {"gaia1": controllability}),
        Mode("evaluate", "fidelity and motion of rollouts against real continuations (GAIA-2: also agents, actions)",
             {"gaia1": evaluate, "gaia2": gaia2_evaluate}),
        Mode("export", "a weights folder (out_dir=) from training checkpoints",
             {"gaia1": export, "gaia2": export_gaia2}),
        Mode("showcase", "one context steered by four commands, and prompts against none (make demo)",
             {"gaia1": showcase}),
        *(Mode(name, GAIA2_SUMMARIES[name], {"gaia2": gaia2_generate}) for name in GAIA2_MODES),
    ]
    return {mode.name: mode for mode in modes}


MODES = _registry()


def mode_run(family: str, name: str) -> Run:
    """The run of mode `name` for model family `family`, or an error listing the modes that family has."""
    mode = MODES.get(name)
    if mode is None or family not in mode.runs:
        have = [m.name for m in MODES.values() if family in m.runs]
        hint = " (mode=encode runs on a video tokenizer ckpt without model=gaia2)" if family == "gaia2" else ""
        raise ValueError(f"model={family} mode={name}: expected one of {have}{hint}")
    return mode.runs[family]
