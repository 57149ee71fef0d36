"""One table from several evaluation runs: GAIA-1 (`generate.py mode=evaluate`, evaluation.json) and GAIA-2
(`generate.py model=gaia2 mode=evaluate`, gaia2_evaluation.json) score rollouts against real continuations with
the same metrics (protocols/evaluate.score); this merges their rows (benchmarks/evaluate_models.py prints it).
"""

from __future__ import annotations

import json
from pathlib import Path

ARROWS = {"psnr": "↑", "ssim": "↑", "lpips": "↓", "fvmd": "↓", "fid": "↓", "fdd": "↓", "agent_iou": "↑"}


def fidelity_rows(out: Path) -> tuple[dict[str, dict[str, float]], str]:
    """The fidelity rows of a GAIA-1 (evaluation.json) or GAIA-2 (gaia2_evaluation.json) run, and its setting."""
    if (out / "gaia2_evaluation.json").is_file():
        results = json.loads((out / "gaia2_evaluation.json").read_text())
        f = results["fidelity"]
        return f["rows"], (f"GAIA-2: {f['clips']} clips (scene × camera: {', '.join(results['cameras'])}), "
                           f"{f['context_frames']} context + {f['generated_frames']} generated frames")
    results = json.loads((out / "evaluation.json").read_text())
    return results["rows"], (f"GAIA-1: {results['contexts']} clips (front camera), {results['context_frames']} "
                             f"context + {results['generated_frames']} generated frames at {results['rate']:g} Hz")


def combined_table(runs: dict[str, Path]) -> str:
    """One markdown table of the fidelity rows of several evaluation run dirs {name: run dir}, with the metrics every
    run computed, and a line per run saying what was scored."""
    loaded = {name: fidelity_rows(path) for name, path in runs.items()}
    metric_sets = [set(next(iter(r.values()))) for r, _ in loaded.values()]
    metrics = [m for m in ARROWS if all(m in s for s in metric_sets)]
    lines = ["| model · rollouts vs real continuations | " + " | ".join(f"{m} {ARROWS[m]}" for m in metrics) + " |",
             "|---" + "|---:" * len(metrics) + "|"]
    for name, (model_rows, _) in loaded.items():
        lines += [f"| {name} · {row} | " + " | ".join(f"{values[m]:.3f}" for m in metrics) + " |"
                  for row, values in model_rows.items()]
    lines += [""] + [setting for _, setting in loaded.values()]
    return "\n".join(lines) + "\n"
