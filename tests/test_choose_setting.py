"""The validation-world choice among trained arms (gaia_app/protocols/choose_setting.py)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from gaia_app.protocols.choose_setting import choose, load_run, main, targets_met


def _result(speed: float, speed_met: bool, curvature_met: bool, night: tuple[float, float],
            snow: tuple[float, float]) -> dict:
    text = {"time_of_day=night": night, "weather=snow": snow, "weather=fog": (0.0, 0.0)}
    return {
        "actions": {
            "rows": {"model": {"speed_contrast": {"mean": speed}, "curvature_contrast": {"mean": 0.03}}},
            "checks": {"speed_contrast": {"model_meets_target": speed_met},
                       "curvature_contrast": {"model_meets_target": curvature_met}},
        },
        "text": {"rows": {"model": {k: {"mean": v[0]} for k, v in text.items()},
                          "floor": {k: {"mean": v[1]} for k, v in text.items()}}},
    }


def _run(root: Path, name: str, result: dict, world: int = 6060, scale: float = 1.5) -> Path:
    folder = root / name
    folder.mkdir()
    (folder / "controllability.json").write_text(json.dumps(result))
    config = {"seed": 42, "weights": f"w_{name}", "context": {"seed": world, "frames": 4}, "seconds": 1.25,
              "controllability": {"contexts": 32}, "guidance": {"scale": scale, "text_scale": 3}}
    (folder / "config_resolved.yaml").write_text(yaml.safe_dump(config))
    return folder


def test_text_targets_need_both_prompted_and_unprompted_shares() -> None:
    met = targets_met(_result(3.0, False, True, night=(0.69, 0.05), snow=(0.94, 0.21)))
    assert met == {"speed_contrast": False, "curvature_contrast": True,
                   "time_of_day=night": False, "weather=snow": False}
    met = targets_met(_result(3.0, True, False, night=(0.70, 0.20), snow=(1.0, 0.0)))
    assert met == {"speed_contrast": True, "curvature_contrast": False,
                   "time_of_day=night": True, "weather=snow": True}


def test_most_targets_win_then_lower_speed_error(tmp_path: Path) -> None:
    arms = {
        "slow": load_run(_run(tmp_path, "slow", _result(3.5, False, False, (1.0, 0.1), (1.0, 0.1)))),  # 2 met
        "fast": load_run(_run(tmp_path, "fast", _result(3.0, False, True, (0.3, 0.1), (1.0, 0.1)))),  # 2 met
        "wild": load_run(_run(tmp_path, "wild", _result(2.0, False, False, (0.3, 0.1), (0.3, 0.1)))),  # 0 met
    }
    choice = choose(arms)
    assert choice["chosen"] == "fast"  # tie on 2 targets, the lower speed error
    assert {name: sum(arm["met"].values()) for name, arm in choice["arms"].items()} == {"slow": 2, "fast": 2, "wild": 0}
    arms["all"] = load_run(_run(tmp_path, "all", _result(3.9, True, True, (1.0, 0.1), (1.0, 0.1))))
    assert choose(arms)["chosen"] == "all"  # more targets beat a lower speed error


def test_runs_on_other_worlds_or_protocols_are_refused(tmp_path: Path) -> None:
    good = _result(3.0, False, True, (1.0, 0.1), (1.0, 0.1))
    a = load_run(_run(tmp_path, "a", good))
    with pytest.raises(ValueError, match=r"b.*context\.seed"):
        choose({"a": a, "b": load_run(_run(tmp_path, "b", good, world=5050))})
    with pytest.raises(ValueError, match=r"c.*guidance\.scale"):
        choose({"a": a, "c": load_run(_run(tmp_path, "c", good, scale=3.0))})
    with pytest.raises(ValueError, match="at least 2 arms"):
        choose({"a": a})


def test_cli_writes_choice_and_names_a_missing_file(tmp_path: Path) -> None:
    a = _run(tmp_path, "a", _result(3.0, False, True, (1.0, 0.1), (1.0, 0.1)))
    b = _run(tmp_path, "b", _result(2.5, True, True, (1.0, 0.1), (1.0, 0.1)))
    choice = main(["--arm", f"x={a}", "--arm", f"y={b}", "--out", str(tmp_path / "out")])
    assert choice["chosen"] == "y"
    assert json.loads((tmp_path / "out" / "choice.json").read_text())["chosen"] == "y"
    assert "chosen: **y**" in (tmp_path / "out" / "choice.md").read_text()
    (b / "config_resolved.yaml").unlink()
    with pytest.raises(FileNotFoundError, match="config_resolved.yaml"):
        main(["--arm", f"x={a}", "--arm", f"y={b}", "--out", str(tmp_path / "out")])
    with pytest.raises(ValueError, match="NAME=DIR"):
        main(["--arm", str(a), "--arm", f"y={b}", "--out", str(tmp_path / "out")])
