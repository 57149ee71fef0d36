"""benchmarks/paper_faithful_figure.py (issue 50, item 1): the study's points, the two figures drawn from them, and
the reading of where a line through an arm's budgets in log FLOPs reaches a target."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from gaia_app.eval.intervals import mean_interval
from gaia_app.protocols.choose_setting import chosen_by_rule
from tests.conftest import load_benchmark

ROOT = Path(__file__).resolve().parents[1]


def test_a_line_through_the_budgets_reaches_the_target_where_it_should() -> None:
    bench = load_benchmark("paper_faithful_figure")
    # 3.0 at 1e14, 2.0 at 1e15: one unit per decade, so 1.0 at 1e16, ten times the largest budget
    assert bench.crossing([1e14, 1e15], [3.0, 2.0], 1.0, lower_is_better=True) == "≈ 1.0e+16 FLOPs (10× the largest)"
    assert bench.crossing([1e14, 1e15], [3.0, 2.0], 2.5, lower_is_better=True) == "met"
    assert bench.crossing([1e14, 1e15], [2.0, 3.0], 1.0, lower_is_better=True) == "moving away"
    assert bench.crossing([1e14, 1e15], [0.2, 0.4], 0.8, lower_is_better=False) == "≈ 1.0e+17 FLOPs (100× the largest)"
    assert bench.crossing([1e14], [3.0], 1.0, lower_is_better=True) == "one budget"
    # 0.01 per decade from 0.97: 2.0 is a hundred decades away, so the line is read as flat
    assert bench.crossing([1e14, 1e15], [0.97, 0.98], 2.0, lower_is_better=False) == "flat: beyond 10^6× the largest"


def test_the_study_draws_both_figures_and_reads_every_arm_and_metric(tmp_path: Path) -> None:
    bench = load_benchmark("paper_faithful_figure")
    rows = bench.main(["--out", str(tmp_path), "--json", str(tmp_path / "crossings.json")])
    for name in ("paper_faithful_gaia1.png", "paper_faithful_gaia2.png"):
        assert (tmp_path / name).stat().st_size > 20_000, name
    metrics = {(r["family"], r["arm"], r["metric"]) for r in rows}
    for arm in ("paper", "shortcut"):
        assert {("GAIA-1", arm, m) for m in ("speed", "curvature", "night prompted", "snow unprompted")} <= metrics
        assert {("GAIA-2", arm, m) for m in ("speed", "curvature", "agent ratio")} <= metrics
    by_key = {(r["family"], r["arm"], r["metric"]): r["crossing"] for r in rows}
    # the study's readings (docs/paper_faithful.md): GAIA-1's paper arm meets curvature at the GPU budget, not speed
    assert by_key[("GAIA-1", "paper", "curvature")] == "met"
    assert by_key[("GAIA-1", "paper", "speed")].startswith("≈")
    assert by_key[("GAIA-2", "paper", "agent ratio")] == "one budget"
    # GAIA-2's onset arm: more budget takes its curvature off the floor to the figure's target at 8× (world 5111);
    # its agents move slowly (1.0× → 1.4×), so their line reaches 2× only tens of times past the largest budget
    assert by_key[("GAIA-2", "paper_onsets", "curvature")] == "met"
    # read by the twin probe (which passes its check), the onset arm's speed error is still far above its target
    assert by_key[("GAIA-2", "paper_onsets", "speed (twin probe)")].startswith("≈")
    agents = by_key[("GAIA-2", "paper_onsets", "agent ratio")]
    assert agents == "≈ 9.6e+16 FLOPs (45× the largest)", agents
    assert json.loads((tmp_path / "crossings.json").read_text()) == rows


def test_every_point_is_the_one_its_table_gives() -> None:
    """The JSON and docs/paper_faithful.md must not drift apart: each point's contrast errors, text shares and agent
    IoU are in its section of the doc, and the doc's crossing table is the script's."""
    bench = load_benchmark("paper_faithful_figure")
    doc = (ROOT / "docs" / "paper_faithful.md").read_text()
    study = bench.load_study()
    for family in ("gaia1", "gaia2"):
        for point in study[family]["points"]:
            section = section_of(doc, point["source"])
            where = (family, point["arm"], point["budget"])
            for metric, digits in (("speed", 3), ("curvature", 4)):
                mean, half = point[metric]
                assert f"{mean:.{digits}f} ± {half:.{digits}f}" in section, (*where, metric)
            for prompt, shares in point.get("text", {}).items():
                prompted, unprompted = (k / n for k, n in (shares["prompted"], shares["unprompted"]))
                assert f"{prompted:.2f} / {unprompted:.2f}" in section, (*where, prompt)
            for key, (mean, low, high) in point.get("agent_iou", {}).items():
                assert f"{mean:.3f} [{low:.3f}, {high:.3f}]" in section, (*where, key)
    # the twin probe's speed readings (GAIA-2) sit in the section that introduced the probe, or in the point's own
    twin_section = section_of(doc, study["gaia2"]["speed_twin_source"])
    read = [p for p in study["gaia2"]["points"] if "speed_twin" in p]
    assert len(read) == 4 and f"{study['gaia2']['targets']['speed_twin']:.3f}" in twin_section
    for point in read:
        mean, half = point["speed_twin"]
        where = twin_section + section_of(doc, point["source"])
        assert f"{mean:.3f} ± {half:.3f}" in where, (point["arm"], point["budget"], "speed_twin")
    speed = next(r for r in bench.crossings(study) if r["arm"] == "paper" and r["metric"] == "speed")
    assert speed["crossing"] == "≈ 1.4e+19 FLOPs (1075× the largest)" and "1 075× the GPU budget" in doc
    # the GAIA-2 onset arm's twin-probe speed line through its four budgets, as the doc's table gives it
    twin = next(r for r in bench.crossings(study) if r["arm"] == "paper_onsets" and r["metric"] == "speed (twin probe)")
    assert twin["crossing"] == "≈ 2.0e+18 FLOPs (923× the largest)" and "≈ 2.0e+18 FLOPs (923× the largest" in doc


def test_the_guidance_chosen_on_the_validation_world_is_the_docs_and_meets_curvature_on_two_worlds_of_three() -> None:
    """The onset arm at 8×: the scale its rule picks from the validation world's readings, and the held-out worlds'
    readings at that scale, as the doc gives them; curvature met on 5111 and 6161 by the point estimate and missed on
    7171, speed missed on all three."""
    bench = load_benchmark("paper_faithful_figure")
    doc = (ROOT / "docs" / "paper_faithful.md").read_text()
    point = bench.load_study()["gaia2"]["points"][-1]
    chosen, section = point["chosen_guidance"], section_of(doc, point["source"])
    validation = chosen["validation"]["curvature"]
    assert int(min(validation, key=lambda scale: validation[scale][0])) == chosen["scale"] == 2
    for scale, (mean, half) in validation.items():
        assert f"{mean:.4f} ± {half:.4f}" in section, ("validation", scale)
    assert set(chosen["scored"]) == {"5111", "6161", "7171"}
    met = set()
    for world, reading in chosen["scored"].items():
        (curvature, c_half), (speed, s_half) = reading["curvature"], reading["speed_twin"]
        assert f"{curvature:.4f} ±" in section and f"{c_half:.4f}" in section, world
        assert f"{speed:.3f} ± {s_half:.3f}" in section, world
        assert f"{reading['targets']['curvature']:.4f}" in section, world
        assert speed > reading["targets"]["speed_twin"], world
        if curvature <= reading["targets"]["curvature"]:
            met.add(world)
    assert met == {"5111", "6161"}


def section_of(doc: str, source: str) -> str:
    """The text of docs/paper_faithful.md under the heading whose anchor `source` names, to the next heading (lines
    in code fences are no headings)."""
    anchor, fenced, found, lines = source.split("#", 1)[1], False, False, []
    for line in doc.splitlines():
        fenced ^= line.startswith("```")
        if line.startswith("#") and not fenced:
            if found:
                break
            heading = line.lstrip("# ").lower()
            found = "".join(c for c in heading if c.isalnum() or c in " -").replace(" ", "-") == anchor
        elif found:
            lines.append(line)
    assert found, f"no heading with anchor #{anchor} in docs/paper_faithful.md"
    return "\n".join(lines)


def test_a_point_without_a_field_is_refused_by_name(tmp_path: Path) -> None:
    bench = load_benchmark("paper_faithful_figure")
    study = json.loads(bench.STUDY.read_text())
    del study["gaia2"]["points"][1]["agent_iou"]
    path = tmp_path / "study.json"
    path.write_text(json.dumps(study))
    with pytest.raises(ValueError, match=r"gaia2\.points\[1\] lacks \['agent_iou'\]"):
        bench.load_study(path)
    study = json.loads(bench.STUDY.read_text())
    del study["gaia2"]["targets"]["speed_twin"]
    path.write_text(json.dumps(study))
    with pytest.raises(ValueError, match=r"gaia2\.points\[\d\] has speed_twin, gaia2\.targets has no speed_twin"):
        bench.load_study(path)


def test_gaia1_paper_arm_on_one_token_set_keeps_its_text_but_not_a_speed_trend() -> None:
    """The GAIA-1 paper arm at 1× and 2× the CPU budget on the same 112-token cache (docs/paper_faithful.md, "GAIA-1
    at 2× the CPU budget"): the speed error does not move beyond either interval, curvature falls, and both text
    targets hold at 2×."""
    study = load_benchmark("paper_faithful_figure").load_study()["gaia1"]
    by_budget = {p["budget"]: p for p in study["points"] if p["arm"] == "paper"}
    one, two = by_budget["CPU, 112 tokens/frame"], by_budget["CPU ×2, 112 tokens/frame"]
    assert two["flops"] / one["flops"] == pytest.approx(2.0, rel=0.01)
    assert abs(two["speed"][0] - one["speed"][0]) < min(one["speed"][1], two["speed"][1])
    assert two["speed"][0] > study["targets"]["speed"]
    assert two["curvature"][0] + two["curvature"][1] < one["curvature"][0] - one["curvature"][1]
    for shares in two["text"].values():
        (k, n), (k0, n0) = shares["prompted"], shares["unprompted"]
        assert k / n >= study["targets"]["prompted"] and k0 / n0 <= study["targets"]["unprompted"]


def test_gaia1_shortcut_arm_at_both_cpu_budgets_meets_control_that_the_paper_arm_misses() -> None:
    """Both GAIA-1 arms at 2× the CPU budget on the same cache (docs/paper_faithful.md, "GAIA-1 at 2× the CPU
    budget", the shortcut arm's table): the shortcut arm meets both control targets at 1× and 2× and neither of its
    errors moves beyond either interval, while both of the paper arm's errors lie clear above the shortcut arm's."""
    study = load_benchmark("paper_faithful_figure").load_study()["gaia1"]
    points = {(p["arm"], p["budget"]): p for p in study["points"]}
    one, two = points[("shortcut", "CPU, 112 tokens/frame")], points[("shortcut", "CPU ×2, 112 tokens/frame")]
    paper_two = points[("paper", "CPU ×2, 112 tokens/frame")]
    assert two["flops"] / one["flops"] == pytest.approx(2.0, rel=0.01)
    for metric in ("speed", "curvature"):
        for point in (one, two):
            assert point[metric][0] <= study["targets"][metric], (point["budget"], metric)
        assert abs(two[metric][0] - one[metric][0]) < min(one[metric][1], two[metric][1]), metric
        assert paper_two[metric][0] - paper_two[metric][1] > two[metric][0] + two[metric][1], metric


def test_gaia1_paper_arm_guidance_chosen_on_a_validation_world_does_not_bring_the_speed() -> None:
    """The 2× paper arm's action guidance (docs/paper_faithful.md, "The paper's own guidance lever"): the scale the
    rule picks from the validation world's readings is the one scored, and on the held-out world 7070 it leaves the
    speed error above its target with a paired change whose interval holds 0, while curvature meets its target."""
    doc = (ROOT / "docs" / "paper_faithful.md").read_text()
    point = next(p for p in load_benchmark("paper_faithful_figure").load_study()["gaia1"]["points"]
                 if p["arm"] == "paper" and p["budget"] == "CPU ×2, 112 tokens/frame")
    chosen, section = point["chosen_guidance"], section_of(doc, point["source"])
    validation = chosen["validation"]
    eligible = [s for s, (mean, _) in validation["curvature"].items() if mean <= validation["targets"]["curvature"]]
    assert float(min(eligible, key=lambda s: validation["speed"][s][0])) == chosen["scale"] == 5
    for metric, digits in (("speed", 3), ("curvature", 4)):
        for mean, half in validation[metric].values():
            assert f"{mean:.{digits}f} ± {half:.{digits}f}" in section, ("validation", metric)
    scored = chosen["scored"]["7070"]
    for reading in ("chosen", "protocol_scale"):
        (speed, s_half), (curvature, c_half) = scored[reading]["speed"], scored[reading]["curvature"]
        assert f"{speed:.3f} ± {s_half:.3f}" in section and f"{curvature:.4f} ± {c_half:.4f}" in section, reading
        assert speed > scored["targets"]["speed"] and curvature <= scored["targets"]["curvature"], reading
    _, low, high = scored["chosen_minus_protocol"]["speed"]
    assert low < 0 < high


def test_gaia1_paper_arm_spending_its_budget_on_size_gains_no_speed_and_loses_curvature_to_windows() -> None:
    """The GAIA-1 paper arm at d 160 × 5 layers on the CPU budget's windows (docs/paper_faithful.md, "Size instead of
    windows"): for less compute than the 2× arm, its speed error stays above the target on both worlds with paired
    differences whose intervals hold 0, while its curvature error is above the 2× arm's on both worlds."""
    study = load_benchmark("paper_faithful_figure").load_study()["gaia1"]
    points = {(p["arm"], p["budget"]): p for p in study["points"]}
    wide = next(p for p in study["points"] if p["arm"] == "paper_wide")
    two = points[("paper", "CPU ×2, 112 tokens/frame")]
    assert 0.8 < wide["flops"] / two["flops"] < 1.0
    assert wide["speed"][0] > study["targets"]["speed"]
    assert wide["second_world"]["7070"]["speed"][0] > two["chosen_guidance"]["scored"]["7070"]["targets"]["speed"]
    for world, differences in wide["minus_paper_2x"].items():
        _, low, high = differences["speed"]
        assert low < 0 < high, world
        _, low, _ = differences["curvature"]
        assert low > 0, world
    section = section_of((ROOT / "docs" / "paper_faithful.md").read_text(), wide["source"])
    mean, half = wide["second_world"]["7070"]["speed"]
    assert f"{mean:.3f} ± {half:.3f}" in section


def test_gaia1_paper_arm_with_speed_entering_at_a_finer_scale_keeps_its_speed_miss() -> None:
    """The GAIA-1 paper arm with speed divided by 2 m/s instead of 8 (docs/paper_faithful.md, "The speed scale"): at the
    CPU budget's compute its speed error stays above the target, and its paired change against the default scale
    holds 0 in its interval."""
    study = load_benchmark("paper_faithful_figure").load_study()["gaia1"]
    scaled = next(p for p in study["points"] if p["arm"] == "paper_speed_scale")
    one = next(p for p in study["points"] if p["arm"] == "paper" and p["budget"] == "CPU, 112 tokens/frame")
    assert scaled["flops"] == one["flops"]
    assert scaled["speed"][0] - scaled["speed"][1] > study["targets"]["speed"]
    _, low, high = scaled["minus_paper_1x"]["5050"]["speed"]
    assert low < 0 < high


def test_gaia1_paper_arm_trained_on_onset_windows_keeps_its_speed_miss_on_both_worlds() -> None:
    """The GAIA-1 paper arm with training windows drawn at command onsets (docs/paper_faithful.md, "The data mix: GAIA-1
    windows at command onsets"): at the CPU budget's compute its speed error stays above the target on world 5050 and
    on 7070, its paired change against uniform windows holds 0 on both, and the section gives both worlds' rows."""
    study = load_benchmark("paper_faithful_figure").load_study()["gaia1"]
    onsets = next(p for p in study["points"] if p["arm"] == "paper_onsets")
    one = next(p for p in study["points"] if p["arm"] == "paper" and p["budget"] == "CPU, 112 tokens/frame")
    assert onsets["flops"] == one["flops"]
    assert onsets["speed"][0] - onsets["speed"][1] > study["targets"]["speed"]
    mean, half = onsets["second_world"]["7070"]["speed"]
    assert mean - half > 2.669  # world 7070's target (docs/paper_faithful.md)
    for world in ("5050", "7070"):
        _, low, high = onsets["minus_paper_1x"][world]["speed"]
        assert low < 0 < high
    section = section_of((ROOT / "docs" / "paper_faithful.md").read_text(), onsets["source"])
    assert f"{mean:.3f} ± {half:.3f}" in section and f"{onsets['speed'][0]:.3f} ± {onsets['speed'][1]:.3f}" in section


def test_gaia1_paper_arm_at_learning_rate_3e3_meets_curvature_and_misses_speed_on_both_worlds() -> None:
    """The GAIA-1 paper arm at the peak learning rate 3e-3 (docs/paper_faithful.md, "The learning rate"): at the CPU
    budget's compute its curvature error meets the target on worlds 5050 and 7070 with a paired drop clear of 0 on
    both, its speed error stays above the target on both, and "night" prompted falls below its target."""
    study = load_benchmark("paper_faithful_figure").load_study()["gaia1"]
    fast = next(p for p in study["points"] if p["arm"] == "paper_lr")
    one = next(p for p in study["points"] if p["arm"] == "paper" and p["budget"] == "CPU, 112 tokens/frame")
    assert fast["flops"] == one["flops"]
    targets = {"5050": (study["targets"]["speed"], study["targets"]["curvature"]), "7070": (2.669, 0.0279)}
    rows = {"5050": fast, "7070": fast["second_world"]["7070"]}
    for world, (speed_target, curvature_target) in targets.items():
        assert rows[world]["curvature"][0] <= curvature_target
        assert rows[world]["speed"][0] > speed_target
        assert fast["minus_paper_1x"][world]["curvature"][2] < 0
    night, of = fast["text"]["night"]["prompted"]
    assert night / of < study["targets"]["prompted"]
    section = section_of((ROOT / "docs" / "paper_faithful.md").read_text(), fast["source"])
    for world in rows:
        mean, half = rows[world]["speed"]
        assert f"{mean:.3f} ± {half:.3f}" in section


def test_gaia1_learning_rate_chosen_on_the_validation_world_meets_curvature_and_misses_speed_on_fresh_worlds() -> None:
    """The learning rate chosen on world 6060 among 1e-3, 3e-3 and 1e-2 (docs/paper_faithful.md, "Choosing the
    learning rate"): the rule (most targets met, then the lower speed error) picks 1e-2 from the recorded readings;
    on the fresh world 8080 and on 5050 its curvature error meets the target with a paired drop against 1e-3 clear
    of 0, and its speed error stays above the target."""
    study = load_benchmark("paper_faithful_figure").load_study()["gaia1"]
    point = next(p for p in study["points"] if p["arm"] == "paper_lr_1e2")
    one = next(p for p in study["points"] if p["arm"] == "paper" and p["budget"] == "CPU, 112 tokens/frame")
    assert point["flops"] == one["flops"]
    choice = point["validation_choice"]
    limits = choice["targets"]
    readings = {name: ((arm["speed"][0] <= limits["speed"]) + (arm["curvature"][0] <= limits["curvature"])
                       + arm["text_met"], arm["speed"][0]) for name, arm in choice["arms"].items()}
    assert chosen_by_rule(readings) == choice["chosen"] == "1e-2"  # the tool's rule on the recorded readings
    targets = {"5050": (study["targets"]["speed"], study["targets"]["curvature"]), "8080": (2.621, 0.0282)}
    rows = {"5050": point, "8080": point["second_world"]["8080"]}
    section = section_of((ROOT / "docs" / "paper_faithful.md").read_text(), point["source"])
    for world, (speed_target, curvature_target) in targets.items():
        assert rows[world]["curvature"][0] <= curvature_target
        assert rows[world]["speed"][0] > speed_target
        assert point["minus_paper_1x"][world]["curvature"][2] < 0
        mean, half = rows[world]["speed"]
        assert f"{mean:.3f} ± {half:.3f}" in section
    night, of = point["text"]["night"]["prompted"]
    assert night / of >= study["targets"]["prompted"]


def test_a_second_seed_of_the_chosen_rate_replicates_curvature_and_not_speed() -> None:
    """Two runs of the 1e-2 recipe (seeds 42 and 43) on world 6060 (docs/paper_faithful.md, "The second seed"): their
    curvature errors differ by far less than the rate's gain over 1e-3 and both meet the target, while their speed
    errors differ with a paired interval clear of 0, as much as the settings' own paired speed differences."""
    study = load_benchmark("paper_faithful_figure").load_study()["gaia1"]
    point = next(p for p in study["points"] if p["arm"] == "paper_lr_1e2")
    seed, choice = point["second_seed"], point["validation_choice"]
    first = choice["arms"]["1e-2"]
    assert seed["world"] == choice["world"]
    assert max(seed["curvature"][0], first["curvature"][0]) <= choice["targets"]["curvature"]
    rate_gain = choice["arms"]["1e-3"]["curvature"][0] - first["curvature"][0]
    assert abs(seed["minus_first_seed"]["curvature"][0]) < rate_gain / 10
    low, high = seed["minus_first_seed"]["curvature"][1:]
    assert low < 0 < high
    mean, low, high = seed["minus_first_seed"]["speed"]
    assert low > 0 and mean >= abs(first["speed"][0] - choice["arms"]["3e-3"]["speed"][0])
    assert abs(seed["speed"][0] - first["speed"][0] - mean) < 0.01
    section = section_of((ROOT / "docs" / "paper_faithful.md").read_text(), point["source"])
    assert f"{seed['speed'][0]:.3f} ± {seed['speed'][1]:.3f}" in section
    assert f"+{mean:.3f} [+{low:.3f}, +{high:.3f}]" in section


def test_over_three_runs_the_chosen_rate_meets_curvature_and_misses_speed_on_a_fresh_world() -> None:
    """Every run of both rates on world 9090, scored once (docs/paper_faithful.md, "Speed over seeds"): over runs, 1e-2
    meets curvature with its whole interval and misses speed by its mean, while single runs fall on both sides of the
    speed target; 1e-3 misses both; action guidance ×3 moves curvature, not speed."""
    study = load_benchmark("paper_faithful_figure").load_study()["gaia1"]
    runs = next(p for p in study["points"] if p["arm"] == "paper_lr_1e2")["over_runs"]
    targets, chosen, base = runs["targets"], runs["1e-2"], runs["1e-3"]
    curvature, speed = mean_interval(chosen["curvature"]), mean_interval(chosen["speed"])
    assert curvature.high <= targets["curvature"] and min(base["curvature"]) > targets["curvature"]
    assert speed.mean > targets["speed"] and min(chosen["speed"]) <= targets["speed"] < max(chosen["speed"])
    assert speed.low < targets["speed"] < speed.high  # over runs, the target lies inside the interval
    assert mean_interval(base["speed"]).mean - speed.mean > 0.5
    paired = runs["minus_1e-3_paired_by_context"]
    assert paired["speed"][2] < 0 and paired["curvature"][2] < 0
    guided = runs["guidance_x3"]["minus_x1.5_paired_by_context"]
    assert guided["speed"][1] < 0 < guided["speed"][2] and guided["curvature"][2] < 0
    section = section_of((ROOT / "docs" / "paper_faithful.md").read_text(), runs["source"])
    assert f"{speed.mean:.3f} [{speed.low:.3f}, {speed.high:.3f}]" in section
    assert f"{curvature.mean:.4f} [{curvature.low:.4f}, {curvature.high:.4f}]" in section


def test_a_runs_speed_ranking_does_not_carry_between_worlds_while_curvature_does() -> None:
    """Seeds 43 and 44 against seed 42 of the 1e-2 recipe, paired by context on worlds 6060 and 9090: the speed
    differences change sign between the worlds, each outside the other world's interval; every run's curvature
    stays below both worlds' targets and far from every 1e-3 run's."""
    study = load_benchmark("paper_faithful_figure").load_study()["gaia1"]
    runs = next(p for p in study["points"] if p["arm"] == "paper_lr_1e2")["over_runs"]
    differences = runs["speed_minus_seed_42_paired_by_context"]
    for seed in ("43", "44"):
        on_6060, low_6060, high_6060 = differences["6060"][seed]
        on_9090, low_9090, high_9090 = differences["9090"][seed]
        assert on_6060 * on_9090 < 0
        assert not low_6060 <= on_9090 <= high_6060 and not low_9090 <= on_6060 <= high_9090
    validation = runs["validation_world"]
    chosen = runs["1e-2"]["curvature"] + validation["1e-2"]["curvature"]
    base = runs["1e-3"]["curvature"] + validation["1e-3"]["curvature"]
    assert max(chosen) < min(runs["targets"]["curvature"], validation["targets"]["curvature"])
    assert min(base) - max(chosen) > 0.015
