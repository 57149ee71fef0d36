"""Choose one setting among trained arms by their controllability on one validation world (issue 50's rule).

    python -m gaia_app.protocols.choose_setting --arm 1e-3=<ctrl dir> --arm 3e-3=<ctrl dir> --out <dir>

Each --arm is NAME=DIR, DIR being a `generate.py mode=controllability` run folder (controllability.json beside
config_resolved.yaml). The rule, written in docs/paper_faithful.md before the arms are scored: the arm that meets
the most of GAIA-1's rollout targets on that world wins (speed and curvature contrast error at most the world's own
floor − ½ (floor − ceiling); "night" and "snow" read in ≥ 70 % of prompted rollouts and ≤ 20 % of unprompted ones);
a tie goes to the lower speed contrast error. The runs must share the world and the protocol (seed, context,
horizon, guidance, number of contexts); only the weights may differ, or the comparison is refused.
Writes choice.json and choice.md into --out.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import yaml

from gaia_app.utils.named_paths import parse_named_paths
from gaia_app.utils.run_dir import atomic_write_text

ACTION_TARGETS = ("speed_contrast", "curvature_contrast")
TEXT_TARGETS = ("time_of_day=night", "weather=snow")
PROMPTED_AT_LEAST = 0.70  # GAIA-1 text target of issue 50: read in ≥ 70 % of prompted rollouts ...
UNPROMPTED_AT_MOST = 0.20  # ... and in ≤ 20 % of unprompted ones
PROTOCOL_KEYS = ("seed", "context.seed", "context.frames", "seconds", "controllability.contexts",
                 "guidance.scale", "guidance.text_scale")


def _select(config: dict, dotted: str) -> Any:
    node: Any = config
    for key in dotted.split("."):
        if not isinstance(node, dict) or key not in node:
            return None
        node = node[key]
    return node


def load_run(folder: Path) -> tuple[dict, dict]:
    """(controllability.json, the protocol settings of config_resolved.yaml) of one run folder."""
    result, config = folder / "controllability.json", folder / "config_resolved.yaml"
    for path in (result, config):
        if not path.is_file():
            raise FileNotFoundError(f"--arm {folder}: no {path.name} (expected a generate.py mode=controllability run)")
    settings = yaml.safe_load(config.read_text())
    return json.loads(result.read_text()), {key: _select(settings, key) for key in PROTOCOL_KEYS}


def protocol_differences(reference: dict, protocol: dict) -> dict[str, tuple[Any, Any]]:
    """{key: (reference value, this value)} of the protocol settings in which two runs differ."""
    return {key: (reference[key], protocol[key]) for key in PROTOCOL_KEYS if reference[key] != protocol[key]}


def targets_met(result: dict) -> dict[str, bool]:
    """Which of GAIA-1's four rollout targets one controllability result meets."""
    for section, keys in (("actions", ACTION_TARGETS), ("text", TEXT_TARGETS)):
        if section not in result:
            raise KeyError(f"controllability.json has no '{section}' section (expected keys {keys})")
    checks, text = result["actions"]["checks"], result["text"]["rows"]
    met = {key: bool(checks[key]["model_meets_target"]) for key in ACTION_TARGETS}
    for key in TEXT_TARGETS:
        met[key] = (text["model"][key]["mean"] >= PROMPTED_AT_LEAST
                    and text["floor"][key]["mean"] <= UNPROMPTED_AT_MOST)
    return met


def summarise(result: dict) -> dict[str, Any]:
    rows = result["actions"]["rows"]["model"]
    text = result["text"]["rows"]
    return {"met": targets_met(result),
            "speed_contrast": rows["speed_contrast"]["mean"],
            "curvature_contrast": rows["curvature_contrast"]["mean"],
            "text": {key: {"prompted": text["model"][key]["mean"], "unprompted": text["floor"][key]["mean"]}
                     for key in TEXT_TARGETS}}


def chosen_by_rule(readings: dict[str, tuple[int, float]]) -> str:
    """The name whose (targets met, speed contrast error) ranks first: most targets, then the lower speed error."""
    return max(readings, key=lambda name: (readings[name][0], -readings[name][1]))


def choose(arms: dict[str, tuple[dict, dict]]) -> dict[str, Any]:
    """The winning arm by the rule above, with every arm's summary; refuses runs that differ in protocol."""
    if len(arms) < 2:
        raise ValueError(f"--arm: a choice needs at least 2 arms, got {len(arms)}")
    names = list(arms)
    reference = arms[names[0]][1]
    for name in names[1:]:
        differing = protocol_differences(reference, arms[name][1])
        if differing:
            raise ValueError(f"--arm {name}: its run differs from {names[0]}'s in {differing}; "
                             "arms are compared on one world under one protocol")
    summaries = {name: summarise(result) for name, (result, _) in arms.items()}
    readings = {name: (sum(arm["met"].values()), arm["speed_contrast"]) for name, arm in summaries.items()}
    return {"chosen": chosen_by_rule(readings), "protocol": reference, "arms": summaries}


def markdown(choice: dict[str, Any]) -> str:
    lines = [f"World {choice['protocol']['context.seed']}; chosen: **{choice['chosen']}** (most targets met, "
             "then the lower speed contrast error)", "",
             "| arm | targets met | speed (m/s) | curvature (1/m) | night prompted / unprompted | snow |",
             "|---|---|---|---|---|---|"]
    for name, arm in choice["arms"].items():
        night, snow = (arm["text"][key] for key in TEXT_TARGETS)
        lines.append(f"| {name} | {sum(arm['met'].values())} of 4 | {arm['speed_contrast']:.3f} | "
                     f"{arm['curvature_contrast']:.4f} | {night['prompted']:.2f} / {night['unprompted']:.2f} | "
                     f"{snow['prompted']:.2f} / {snow['unprompted']:.2f} |")
    return "\n".join(lines) + "\n"


def write_reading(out: Path, stem: str, reading: dict[str, Any], text: str) -> None:
    """<out>/<stem>.json and <stem>.md, each written atomically, and the Markdown printed."""
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / f"{stem}.json", json.dumps(reading, indent=2))
    atomic_write_text(out / f"{stem}.md", text)
    print(text)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--arm", action="append", required=True, help="NAME=controllability run folder")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    choice = choose({name: load_run(folder) for name, folder in parse_named_paths(args.arm, "--arm", "DIR").items()})
    write_reading(args.out, "choice", choice, markdown(choice))
    return choice


if __name__ == "__main__":
    main()
