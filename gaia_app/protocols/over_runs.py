"""A setting's controllability read over several training runs (seeds) on one world (issue 50's seed study).

    python -m gaia_app.protocols.over_runs --run 1e-2=<ctrl dir> --run 1e-2=<ctrl dir> --run 1e-3=<ctrl dir> \
        --run 1e-3=<ctrl dir> --out <dir>

Each --run is SETTING=DIR, DIR a `generate.py mode=controllability` run folder of one trained run; a setting named
again adds a run to it. One run per setting cannot rank settings on speed at the CPU budget (two runs of one recipe
differed by 0.35 m/s, docs/paper_faithful.md "The second seed"), so each setting is read as:

- over runs: the mean of the runs' contrast errors, with a Student-t 95 % interval over runs (the run is the unit,
  so the interval says how far another run of the recipe may land);
- by context: each context's error averaged over the runs, with a t interval over contexts (the runs held fixed);
- against the world's target (floor − ½ (floor − ceiling), the same for every run: the probes and re-simulations
  read the world, not the weights): the over-runs mean meets it or not, and whether the whole interval does.

The first setting is compared with each other one: the difference of over-runs means with a Welch interval, and
the paired-by-context difference of the run-averaged errors. Every run must share the world and the protocol, or
the reading is refused; `--vary KEY` lets settings differ in one protocol key (a sampling setting under comparison,
e.g. `--vary guidance.scale`), which must still agree within a setting.
Writes over_runs.json and over_runs.md into --out.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

import numpy as np

from gaia_app.eval.intervals import Estimate, mean_interval, t_quantile
from gaia_app.protocols.choose_setting import (
    ACTION_TARGETS,
    PROTOCOL_KEYS,
    TEXT_TARGETS,
    load_run,
    protocol_differences,
    summarise,
    write_reading,
)
from gaia_app.utils.named_paths import parse_grouped_paths

TARGET_AGREEMENT = 1e-9  # runs on one world read one target; a larger difference means another world or probe


def check_same_protocol(runs: dict[str, list[tuple[Path, dict, dict]]], varied: tuple[str, ...] = ()) -> dict:
    """The shared protocol settings of every run; an error names the first run that differs and how. A key in
    `varied` (a sampling setting under comparison, e.g. guidance.scale) may differ between settings, never within
    one; it is reported per setting."""
    unknown = set(varied) - set(PROTOCOL_KEYS)
    if unknown:
        raise ValueError(f"--vary {sorted(unknown)}: not a protocol key (one of {PROTOCOL_KEYS})")
    (first_path, _, reference), *_ = next(iter(runs.values()))
    for name, group in runs.items():
        setting_reference = group[0][2]
        for path, _, protocol in group:
            across = {key: value for key, value in protocol_differences(reference, protocol).items()
                      if key not in varied}
            within = {key: value for key, value in protocol_differences(setting_reference, protocol).items()
                      if key in varied}
            if across or within:
                raise ValueError(f"--run {name}={path}: differs from {first_path} in {across or within}; "
                                 "runs are read on one world under one protocol")
    return {key: value for key, value in reference.items() if key not in varied}


def world_target(group: list[tuple[Path, dict, dict]], metric: str) -> float:
    """The one target every run of a group reads for `metric`; an error names a run whose target differs."""
    targets = [(path, result["actions"]["checks"][metric]["target"]) for path, result, _ in group]
    for path, target in targets[1:]:
        if abs(target - targets[0][1]) > TARGET_AGREEMENT:
            raise ValueError(f"--run {path}: its {metric} target {target:.6f} differs from {targets[0][0]}'s "
                             f"{targets[0][1]:.6f}: the runs do not read the same world")
    return float(targets[0][1])


def per_context(group: list[tuple[Path, dict, dict]], metric: str) -> np.ndarray:
    """(runs, contexts) per-context contrast errors of a group; an error names a run with another context count."""
    rows = [np.asarray(result["actions"]["rows"]["model"][metric]["per_context"], dtype=float)
            for _, result, _ in group]
    for (path, _, _), row in zip(group, rows, strict=True):
        if row.shape != rows[0].shape:
            raise ValueError(f"--run {path}: {len(row)} contexts of {metric}, expected {len(rows[0])}")
    return np.stack(rows)


def welch_difference(a: list[float], b: list[float]) -> Estimate:
    """mean(a) − mean(b) with a Welch 95 % interval (df rounded down: the wider interval); infinite below 2 runs."""
    difference = float(np.mean(a) - np.mean(b))
    if len(a) < 2 or len(b) < 2:
        return Estimate(difference, -math.inf, math.inf, len(a) + len(b))
    va, vb = np.var(a, ddof=1) / len(a), np.var(b, ddof=1) / len(b)
    se = math.sqrt(va + vb)
    if se == 0:
        return Estimate(difference, difference, difference, len(a) + len(b))
    df = (va + vb) ** 2 / (va**2 / (len(a) - 1) + vb**2 / (len(b) - 1))
    half = t_quantile(max(1, math.floor(df))) * se
    return Estimate(difference, difference - half, difference + half, len(a) + len(b))


def read_setting(group: list[tuple[Path, dict, dict]]) -> dict[str, Any]:
    """Over-runs and by-context readings of one setting's runs, with the text shares of each run."""
    reading: dict[str, Any] = {"runs": [str(path) for path, _, _ in group]}
    for metric in ACTION_TARGETS:
        errors = per_context(group, metric)
        over_runs = mean_interval(errors.mean(axis=1))
        target = world_target(group, metric)
        reading[metric] = {"per_run": errors.mean(axis=1).tolist(), "over_runs": over_runs.as_dict(),
                           "by_context": mean_interval(errors.mean(axis=0)).as_dict(), "target": target,
                           "mean_meets_target": over_runs.mean <= target,
                           "interval_below_target": over_runs.high <= target}
    texts = [summarise(result)["text"] for _, result, _ in group]
    reading["text"] = {key: {side: [text[key][side] for text in texts] for side in ("prompted", "unprompted")}
                       for key in TEXT_TARGETS}
    return reading


def compare(first: dict, other: dict, groups: tuple[list, list]) -> dict[str, Any]:
    """first − other for each metric: over runs (Welch) and paired by context (run-averaged errors)."""
    out = {}
    for metric in ACTION_TARGETS:
        paired = per_context(groups[0], metric).mean(axis=0) - per_context(groups[1], metric).mean(axis=0)
        out[metric] = {"over_runs": welch_difference(first[metric]["per_run"], other[metric]["per_run"]).as_dict(),
                       "paired_by_context": mean_interval(paired).as_dict()}
    return out


def read_runs(runs: dict[str, list[tuple[Path, dict, dict]]], varied: tuple[str, ...] = ()) -> dict[str, Any]:
    """Every setting's reading and the first setting's differences with each other one."""
    protocol = check_same_protocol(runs, varied)
    settings = {name: read_setting(group) | {"varied": {key: group[0][2][key] for key in varied}}
                for name, group in runs.items()}
    names = list(runs)
    differences = {f"{names[0]} - {name}": compare(settings[names[0]], settings[name], (runs[names[0]], runs[name]))
                   for name in names[1:]}
    return {"protocol": protocol, "settings": settings, "differences": differences}


def _interval(estimate: dict, digits: int) -> str:
    return f"{estimate['mean']:.{digits}f} [{estimate['low']:.{digits}f}, {estimate['high']:.{digits}f}]"


def markdown(reading: dict[str, Any]) -> str:
    digits = {"speed_contrast": 3, "curvature_contrast": 4}
    lines = [f"World {reading['protocol']['context.seed']}: contrast errors over training runs (95 % intervals)", "",
             "| setting | runs | metric | per run | over runs | by context | target | mean meets it |",
             "|---|---|---|---|---|---|---|---|"]
    for name, setting in reading["settings"].items():
        for metric, d in digits.items():
            row = setting[metric]
            per_run = ", ".join(f"{value:.{d}f}" for value in row["per_run"])
            lines.append(f"| {name} | {len(setting['runs'])} | {metric} | {per_run} | "
                         f"{_interval(row['over_runs'], d)} | {_interval(row['by_context'], d)} | "
                         f"{row['target']:.{d}f} | {'yes' if row['mean_meets_target'] else 'no'} |")
    lines.append("")
    for label, difference in reading["differences"].items():
        for metric, d in digits.items():
            row = difference[metric]
            lines.append(f"- {label}, {metric}: over runs {_interval(row['over_runs'], d)}; "
                         f"paired by context {_interval(row['paired_by_context'], d)}")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--run", action="append", required=True, help="SETTING=controllability run folder")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--vary", action="append", default=[],
                        help="a protocol key the settings may differ in (e.g. guidance.scale), one per --vary")
    args = parser.parse_args(argv)
    groups = parse_grouped_paths(args.run, "--run", "DIR")
    runs = {name: [(path, *load_run(path)) for path in paths] for name, paths in groups.items()}
    reading = read_runs(runs, tuple(args.vary))
    write_reading(args.out, "over_runs", reading, markdown(reading))
    return reading


if __name__ == "__main__":
    main()
