"""`generate(cfg)`: run trained checkpoints or shipped weights in one of the modes of the registry
(gaia_app/tasks/modes.py; each mode's settings in conf/mode/<name>.yaml): tokenizer modes (reconstruct, tokenize,
encode), GAIA-1 rollouts and their protocols (controllability, evaluate, showcase, export), and with model=gaia2 the
GAIA-2 latent world model (scratch, rollout, inpaint, edit, evaluate, export).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import lightning as L
from omegaconf import DictConfig

from gaia_app.tasks.modes import mode_run
from gaia_app.tasks.settings import GENERATE_RULES, check_settings
from gaia_app.utils.run_dir import atomic_write_text, save_resolved_config

log = logging.getLogger(__name__)


def generate(cfg: DictConfig) -> dict[str, Any]:
    """Run `cfg.mode` of the model family `cfg.model.family`, write results.json in the run dir and return the
    results."""
    check_settings(cfg, GENERATE_RULES)
    family = cfg.model.get("family")
    if family not in ("gaia1", "gaia2"):
        raise ValueError(f"model={cfg.model}: generate.py runs the model families gaia1 or gaia2 "
                         "(conf/model/gaia*.yaml)")
    run = mode_run(family, cfg.mode)
    L.seed_everything(cfg.seed, workers=True)
    run_dir = Path(cfg.paths.output_dir)
    save_resolved_config(cfg, run_dir)
    results = run(cfg, run_dir)
    atomic_write_text(run_dir / "results.json", json.dumps(results, indent=2))
    log.info("mode=%s done; results.json in %s", cfg.mode, run_dir)
    return {"results": results, "run_dir": run_dir}
