"""Evaluation protocols and the settings-to-pipeline set-up they share (DESIGN.md §3, `protocols/`).

`generate.py` (gaia_app/tasks) and the scripts under benchmarks/ both run these; benchmarks never import tasks/.
- `loading`: the GAIA-1 and GAIA-2 pipelines a config names (shipped weights or training checkpoints).
- `gaia2_context`: the clip, commands and pipeline call of a GAIA-2 generation mode, from a config.
- `controllability`, `evaluate`: GAIA-1 action / text adherence and fidelity against real continuations.
- `gaia2_actions`, `gaia2_evaluate`: GAIA-2 action adherence, agent control and fidelity tables.
- `world_model_report`: held-out cross-entropy of a GAIA-1 world model per conditioning mode.
- `scaling`: the scaling-law sweep's Hydra callbacks and fit.
"""
