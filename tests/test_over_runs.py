"""A setting read over several training runs on one world (gaia_app/protocols/over_runs.py)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import yaml

from gaia_app.eval.intervals import t_quantile
from gaia_app.protocols.over_runs import main, welch_difference
from gaia_app.utils.named_paths import parse_grouped_paths, parse_named_paths


def _run(root: Path, name: str, speed: list[float], curvature: float = 0.02, world: int = 6060,
         speed_target: float = 2.5, scale: float = 1.5) -> Path:
    """A controllability run folder whose speed errors per context are `speed`."""
    folder = root / name
    folder.mkdir()
    text = {"time_of_day=night": 0.9, "weather=snow": 0.8}
    rows = {"speed_contrast": {"mean": sum(speed) / len(speed), "per_context": speed},
            "curvature_contrast": {"mean": curvature, "per_context": [curvature] * len(speed)}}
    result = {"actions": {"rows": {"model": rows},
                          "checks": {"speed_contrast": {"target": speed_target, "model_meets_target": False},
                                     "curvature_contrast": {"target": 0.028, "model_meets_target": True}}},
              "text": {"rows": {"model": {k: {"mean": v} for k, v in text.items()},
                                "floor": {k: {"mean": 0.1} for k in text}}}}
    (folder / "controllability.json").write_text(json.dumps(result))
    config = {"seed": 42, "context": {"seed": world, "frames": 4}, "seconds": 1.25,
              "controllability": {"contexts": len(speed)}, "guidance": {"scale": scale, "text_scale": 3}}
    (folder / "config_resolved.yaml").write_text(yaml.safe_dump(config))
    return folder


def test_a_setting_is_read_over_its_runs_and_against_the_world_target(tmp_path: Path) -> None:
    a1 = _run(tmp_path, "a1", [2.0, 3.0, 2.0, 3.0])  # run mean 2.5
    a2 = _run(tmp_path, "a2", [2.0, 2.0, 2.0, 2.0])  # 2.0
    a3 = _run(tmp_path, "a3", [1.0, 2.0, 1.0, 2.0])  # 1.5
    b1 = _run(tmp_path, "b1", [3.0, 3.0, 4.0, 4.0])  # 3.5
    b2 = _run(tmp_path, "b2", [3.0, 3.0, 3.0, 3.0])  # 3.0
    runs = [f"a={a1}", f"a={a2}", f"a={a3}", f"b={b1}", f"b={b2}"]
    reading = main([arg for run in runs for arg in ("--run", run)] + ["--out", str(tmp_path / "out")])
    speed_a = reading["settings"]["a"]["speed_contrast"]
    assert speed_a["per_run"] == [2.5, 2.0, 1.5]
    # over runs: mean 2.0, sd 0.5 over 3 runs, t(2) = 4.303
    assert speed_a["over_runs"]["mean"] == pytest.approx(2.0)
    assert speed_a["over_runs"]["high"] - 2.0 == pytest.approx(4.303 * 0.5 / math.sqrt(3), rel=1e-3)
    assert speed_a["by_context"]["mean"] == pytest.approx(2.0) and speed_a["by_context"]["n"] == 4
    assert speed_a["mean_meets_target"] and not speed_a["interval_below_target"]  # the interval crosses 2.5
    speed_b = reading["settings"]["b"]["speed_contrast"]
    assert speed_b["over_runs"]["mean"] == pytest.approx(3.25) and not speed_b["mean_meets_target"]
    difference = reading["differences"]["a - b"]["speed_contrast"]
    assert difference["over_runs"]["mean"] == pytest.approx(-1.25)
    # by context: a averages (5/3, 7/3, 5/3, 7/3), b (3, 3, 3.5, 3.5)
    assert difference["paired_by_context"]["mean"] == pytest.approx(-1.25) and difference["paired_by_context"]["n"] == 4
    assert reading["settings"]["a"]["text"]["time_of_day=night"]["prompted"] == [0.9, 0.9, 0.9]
    written = (tmp_path / "out" / "over_runs.md").read_text()
    assert "| a | 3 | speed_contrast | 2.500, 2.000, 1.500 | 2.000 [" in written
    assert json.loads((tmp_path / "out" / "over_runs.json").read_text())["protocol"]["context.seed"] == 6060


def test_welch_interval_of_two_settings() -> None:
    difference = welch_difference([1.0, 2.0, 3.0], [1.0, 3.0])  # variances 1/3 and 2/2; df = (1/3+1)²/(1/18+1)
    se, df = math.sqrt(1 / 3 + 1), (1 / 3 + 1) ** 2 / ((1 / 3) ** 2 / 2 + 1**2 / 1)
    assert difference.mean == pytest.approx(0.0)
    assert difference.high == pytest.approx(t_quantile(math.floor(df)) * se)
    single = welch_difference([1.0], [2.0, 3.0])
    assert single.mean == pytest.approx(-1.5) and math.isinf(single.high)


def test_runs_of_other_worlds_protocols_or_context_counts_are_refused(tmp_path: Path) -> None:
    a = _run(tmp_path, "a", [2.0, 3.0])
    other_world = _run(tmp_path, "w", [2.0, 3.0], world=5050)
    other_target = _run(tmp_path, "t", [2.0, 3.0], speed_target=2.7)
    with pytest.raises(ValueError, match=r"--run b=.*w.*context\.seed"):
        main(["--run", f"a={a}", "--run", f"b={other_world}", "--out", str(tmp_path / "o")])
    with pytest.raises(ValueError, match=r"speed_contrast target 2\.700000 differs"):
        main(["--run", f"a={a}", "--run", f"a={other_target}", "--out", str(tmp_path / "o")])
    (tmp_path / "a" / "controllability.json").unlink()
    with pytest.raises(FileNotFoundError, match="controllability.json"):
        main(["--run", f"a={a}", "--out", str(tmp_path / "o")])


def test_named_and_grouped_paths(tmp_path: Path) -> None:
    x, y = tmp_path / "x", tmp_path / "y"
    x.mkdir(), y.mkdir()
    assert parse_grouped_paths([f"a={x}", f"b={y}"], "--run") == {"a": [x], "b": [y]}
    assert parse_grouped_paths([f"a={x}", f"a={y}"], "--run") == {"a": [x, y]}
    with pytest.raises(ValueError, match="given twice"):
        parse_grouped_paths([f"a={x}", f"b={x}"], "--run")
    with pytest.raises(ValueError, match="'a' is given twice"):
        parse_named_paths([f"a={x}", f"a={y}"], "--model")
    with pytest.raises(ValueError, match="expected NAME=DIR"):
        parse_grouped_paths(["a"], "--run", "DIR")


def test_settings_may_differ_in_a_varied_sampling_key_but_not_within_one(tmp_path: Path) -> None:
    low = [_run(tmp_path, f"low{i}", [3.0, 3.0], scale=1.5) for i in range(2)]
    high = [_run(tmp_path, f"high{i}", [2.0, 2.4], scale=3.0) for i in range(2)]
    args = ["--run", f"x1.5={low[0]}", "--run", f"x1.5={low[1]}", "--run", f"x3={high[0]}", "--run", f"x3={high[1]}"]
    with pytest.raises(ValueError, match=r"guidance\.scale"):
        main(args + ["--out", str(tmp_path / "o")])
    reading = main(args + ["--vary", "guidance.scale", "--out", str(tmp_path / "o")])
    assert reading["settings"]["x3"]["varied"] == {"guidance.scale": 3.0}
    assert "guidance.scale" not in reading["protocol"]
    assert reading["differences"]["x1.5 - x3"]["speed_contrast"]["paired_by_context"]["mean"] == pytest.approx(0.8)
    mixed = ["--run", f"x1.5={low[0]}", "--run", f"x1.5={high[0]}"]
    with pytest.raises(ValueError, match=r"x1\.5=.*high0.*guidance\.scale"):
        main(mixed + ["--vary", "guidance.scale", "--out", str(tmp_path / "o")])
    with pytest.raises(ValueError, match="not a protocol key"):
        main(args + ["--vary", "model.depth", "--out", str(tmp_path / "o")])
