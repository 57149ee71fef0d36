"""benchmarks/eval_latent_world_model.py: context prediction of a latent world model against repeating the last
context step, with a mean-of-samples point forecast and paired intervals (docs/latent_world_model.md)."""

from __future__ import annotations

import importlib.util
import re
import sys

import pytest
import torch

from gaia_app.protocols import gaia2_evaluate
from tests.conftest import ROOT
from tests.test_gaia2_generate import checkpoints  # noqa: F401  (a fixture)

pytestmark = pytest.mark.usefixtures("one_thread")


# GAIA-2 benchmark scripts run end to end at their protocols' cost, mostly on the shipped weights (6–35 s each): the
# slow tier (`make test-slow`, CI). Every gaia_app line they reach is reached by the quick tier too
# (docs/benchmarks.md, "two tiers").
BENCHMARK_SCRIPT = pytest.mark.slow


def load_benchmark(name: str):
    """The module of benchmarks/<name>.py (the benchmarks folder is scripts, not a package)."""
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("eval_latent_world_model")


def test_every_row_has_an_interval_and_its_difference_to_repeat(bench, checkpoints, monkeypatch, capsys) -> None:  # noqa: F811
    monkeypatch.setattr(sys, "argv", ["eval", "--world-model-ckpt", str(checkpoints["world_model"]),
                                      "--tokenizer-ckpt", str(checkpoints["tokenizer"]),
                                      "--latents", str(checkpoints["latents"] / "val"),
                                      "--solver-steps", "2", "--samples", "3"])
    bench.main()
    out = capsys.readouterr().out
    rows = dict(re.findall(r"^\| (world model[^|]*|repeat last context step|mean latent) \| (.*) \|$", out,
                           re.MULTILINE))
    assert set(rows) == {"world model", "world model, mean of 3 samples", "repeat last context step", "mean latent"}
    assert all(re.fullmatch(r"[\d.]+ \| [\d.]+ ± [\d.]+ \| -?[\d.]+ ± [\d.]+", v) for v in rows.values())
    assert rows["repeat last context step"].endswith("| 0.00 ± 0.00")


def test_a_weights_folder_replaces_the_two_checkpoints(bench, checkpoints, monkeypatch, capsys) -> None:  # noqa: F811
    """--weights gaia2 scores the shipped world model through its own tokenizer; neither source is refused."""
    latents = ["--latents", str(checkpoints["latents"] / "val"), "--solver-steps", "2"]
    monkeypatch.setattr(sys, "argv", ["eval", "--weights", "gaia2", *latents])
    bench.main()
    assert re.search(r"^\| world model \| [\d.]+ \| [\d.]+ ± [\d.]+ \|", capsys.readouterr().out, re.MULTILINE)
    monkeypatch.setattr(sys, "argv", ["eval", *latents])
    with pytest.raises(SystemExit):
        bench.main()
    assert "give --weights, or --world-model-ckpt and --tokenizer-ckpt" in capsys.readouterr().err


def test_interval_is_the_mean_and_a_normal_half_width(bench) -> None:
    assert bench.interval(torch.tensor([1.0, 3.0])) == f"2.00 ± {1.96 * 2 ** 0.5 / 2 ** 0.5:.2f}"


@BENCHMARK_SCRIPT
def test_condition_gain_reads_a_weights_folder(checkpoints, monkeypatch, capsys) -> None:  # noqa: F811
    """benchmarks/gaia2_condition_gain.py --weights gaia2: the teacher-forced gains of the shipped world model."""
    module = load_benchmark("gaia2_condition_gain")
    monkeypatch.setattr(sys, "argv", ["gain", "--weights", "gaia2", "--latents", str(checkpoints["latents"] / "val")])
    module.main()
    out = capsys.readouterr().out
    assert re.search(r"action discrimination with agents +[+-][\d.]+ \[[+-][\d.]+, [+-][\d.]+\]", out), out
    monkeypatch.setattr(sys, "argv", ["gain", "--weights", "gaia2", "--latents", str(checkpoints["latents"] / "val"),
                                      "--taus", "0.05"])
    module.main()
    out = capsys.readouterr().out
    assert "at τ 0.05 " in out and "at τ 0.25" not in out


@BENCHMARK_SCRIPT
def test_gaia2_probe_quality_scores_the_ceiling_against_the_reference() -> None:
    """benchmarks/gaia2_probe_quality.py: the evaluation's action probe, model-free, on two scenes."""
    module = load_benchmark("gaia2_probe_quality")
    result = module.probe_quality(["model.evaluate.contexts=2", "model.evaluate.probe_clips=4",
                                   "model.evaluate.probe_steps=3"])
    for metric in ("speed_contrast", "curvature_contrast"):
        row = result[metric]
        assert row["reference"] > 0 and row["ratio"] == pytest.approx(row["ceiling"] / row["reference"])
        assert row["target"] == pytest.approx((row["reference"] + row["ceiling"]) / 2) and row["tokenized"] >= 0
    # the reference ignores the commands: its probed contrast is ~0, so its error is the commanded difference
    assert result["curvature_contrast"]["reference"] == pytest.approx(0.04, abs=0.01)


@BENCHMARK_SCRIPT
def test_gaia2_action_adherence_reads_speed_with_the_twin_probe(tmp_path) -> None:
    """model.evaluate.speed_probe=twin: the speed contrast is the twin probe's reading, the pair probe's is kept, and
    rows whose futures ignore the command (floor, reference) read exactly 0 of it; the twin probe is saved with the run
    and a later run loads it and reads the same."""
    from gaia_app.protocols import gaia2_twin_probe

    module = load_benchmark("gaia2_action_adherence")
    tiny = ["model.evaluate.contexts=1", "model.evaluate.probe_clips=2", "model.evaluate.probe_steps=2",
            "model.sampler.steps=2", "model.guidance.conditions=[action]", "model.steps=3",
            "model.evaluate.speed_probe=twin"]
    result = module.main(["--weights", "gaia2", "--out", str(tmp_path / "out"), "--", *tiny])
    table = result["tables"]["gaia2"]
    assert table["speed_probe"] == "twin" and "fit" in result["twin_probe_fit"]
    for name, row in table["rows"].items():
        assert {"speed_contrast", "speed_contrast_pair"} <= set(row) and "speed_contrast_pair" in row["realised"]
        if name in ("floor", "reference"):
            realised = row["realised"]["speed_contrast"]
            assert realised["mean"] == 0 and row["speed_contrast"]["mean"] == pytest.approx(realised["commanded"])
    assert "read by the twin probe" in (tmp_path / "out" / "action_adherence.md").read_text()
    saved = tmp_path / "out" / "twin_probe"
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(gaia2_twin_probe, "train_twin_probe", lambda *a, **k: pytest.fail("trained a second probe"))
        again = module.main(["--weights", "gaia2", "--probe", str(tmp_path / "out" / "action_probe"), "--", *tiny,
                             f"model.evaluate.twin_probe={saved}"])
    assert again["tables"]["gaia2"]["rows"]["ceiling"] == table["rows"]["ceiling"]


@BENCHMARK_SCRIPT
def test_gaia2_action_adherence_scores_folders_and_scales_side_by_side_on_one_probe(tmp_path) -> None:
    """benchmarks/gaia2_action_adherence.py: every folder × guidance scale is scored on one probe with the same scenes
    and noise: a copy of the shipped folder gets the same table as the original, another guidance scale and (in the
    fidelity-only run below) a folder with other world-model weights get other futures (so no folder or scale is
    ignored), and the files carry one table per variant. The real continuations (the ceiling) are rendered once for
    all variants."""
    import shutil

    from hydra.errors import InstantiationException
    from safetensors.torch import load_file, save_file

    from gaia_app.protocols import gaia2_action_probe, gaia2_actions
    from gaia_app.weights.folders import shipped_folder

    module = load_benchmark("gaia2_action_adherence")
    copy = shutil.copytree(shipped_folder("gaia2"), tmp_path / "copy")
    other = shutil.copytree(shipped_folder("gaia2"), tmp_path / "other")
    weights = load_file(other / "latent_world_model.safetensors")
    save_file({name: tensor * 0.9 for name, tensor in weights.items()}, other / "latent_world_model.safetensors")
    rendered = []
    resimulated = gaia2_actions.resimulated

    def counted(*args, **kwargs):
        rendered.append(args[1])
        return resimulated(*args, **kwargs)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(gaia2_actions, "resimulated", counted)
        result = module.main(["--weights", "gaia2", str(copy), "--scales", "0", "4", "--tables", "actions",
                              "fidelity", "--out", str(tmp_path / "out"), "evaluate.metrics=[psnr,fvmd]",
                              "model.evaluate.contexts=1", "model.evaluate.noise_draws=2",
                              "model.evaluate.probe_clips=2", "model.evaluate.probe_steps=2", "model.sampler.steps=2",
                              "model.guidance.conditions=[action]", "model.steps=3"])
    tables = result["tables"]
    assert len(tables) == 4 and len(rendered) == 4  # 1 scene × 4 commands, rendered for the first variant only
    original, copied = tables["gaia2, guidance ×0"], tables[f"{copy}, guidance ×0"]
    # model.steps=3: two context steps and one generated latent step, so 2 scored frame pairs (the shipped config
    # generates 2 steps in chunks; chunked rollouts are tested in tests/test_gaia2_generate.py)
    assert original["probe_stride"] == 2 and original["scored_steps"] == 2 and original["noise_draws"] == 2
    assert original["rows"]["model"]["draws"] == 2 and original["rows"]["ceiling"]["draws"] == 1
    for name in ("ceiling", "model", "floor"):
        assert original["rows"][name]["curvature_contrast"] == copied["rows"][name]["curvature_contrast"]
    def realised(table: dict) -> list[float]:
        return table["rows"]["model"]["realised"]["speed_contrast"]["per_context"]
    assert realised(tables["gaia2, guidance ×4"]) != realised(original)
    assert tables[f"{copy}, guidance ×4"]["rows"]["ceiling"] == original["rows"]["ceiling"]  # one probe, same scenes
    table = (tmp_path / "out" / "action_adherence.md").read_text()
    assert table.count("| model, commanded actions |") == 4 and f"### weights={copy}, guidance ×4" in table
    fidelity = result["fidelity"]
    assert fidelity[f"{copy}, guidance ×0"] == fidelity["gaia2, guidance ×0"]  # the same scenes and noise
    assert (fidelity["gaia2, guidance ×4"]["rows"]["model (rollouts)"]
            != fidelity["gaia2, guidance ×0"]["rows"]["model (rollouts)"])
    assert table.count("| gaia2, guidance ×") == 2 and "| held frame (floor) |" in table and "fvmd ↓" in table
    assert table.count("paired by scene") == 3 and "speed contrast +0.000 [" in table  # the copy's ×0 table: no change
    # the probe the run trained is saved with it; a later run loads it instead of training one, and reads the same
    saved = tmp_path / "out" / "action_probe"
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(gaia2_action_probe, "train_action_probe", lambda *a: pytest.fail("trained a second probe"))
        reloaded = module.main(["--weights", "gaia2", "--probe", str(saved), "--", "model.evaluate.contexts=1",
                                "model.sampler.steps=2", "model.guidance.conditions=[action]", "model.steps=3"])
    assert reloaded["probe_fit"]["loaded_from"] == str(saved)
    assert reloaded["tables"]["gaia2"]["rows"]["ceiling"] == original["rows"]["ceiling"]
    with pytest.raises(ValueError, match="probe_stride=5"):
        module.main(["--weights", "gaia2", "--", "model.evaluate.probe_stride=5"])
    alone = module.main(["--weights", "gaia2", str(other), "--tables", "fidelity", "--", "evaluate.metrics=[psnr]",
                         "model.evaluate.contexts=1", "model.sampler.steps=2"])
    assert alone["tables"] == {} and alone["probe_fit"] is None and list(alone["fidelity"]) == ["gaia2", str(other)]
    assert (alone["fidelity"][str(other)]["rows"]["model (rollouts)"]
            != alone["fidelity"]["gaia2"]["rows"]["model (rollouts)"])  # other weights, other futures
    with pytest.raises(ValueError, match="drop agent_iou"):
        module.main(["--weights", "gaia2", "--tables", "fidelity"])
    # guidance intervals: no solver step of a 2-step sampler lies in τ ∈ [0.9, 1], so ×4 there is the unguided model
    spans = module.main(["--weights", "gaia2", "--scales", "0", "4", "--intervals", "0,1", "0.9,1", "--tables",
                         "fidelity", "--", "evaluate.metrics=[psnr]", "model.evaluate.contexts=1",
                         "model.sampler.steps=2", "model.guidance.conditions=[action]"])["fidelity"]
    unguided = spans["gaia2, guidance ×0, τ ∈ [0, 1]"]
    assert spans["gaia2, guidance ×4, τ ∈ [0.9, 1]"] == unguided == spans["gaia2, guidance ×0, τ ∈ [0.9, 1]"]
    assert spans["gaia2, guidance ×4, τ ∈ [0, 1]"]["rows"]["model (rollouts)"] != unguided["rows"]["model (rollouts)"]
    with pytest.raises(InstantiationException, match=r"guidance.interval=\[0.5, 0.2\]: expected \[lo, hi\]"):
        module.main(["--weights", "gaia2", "--scales", "4", "--intervals", "0.5,0.2", "--tables", "fidelity", "--",
                     "evaluate.metrics=[psnr]"])
    with pytest.raises(ValueError, match="noise_draws=0"):
        module.main(["--weights", "gaia2", "--", "model.evaluate.noise_draws=0", "model.evaluate.contexts=1",
                     "model.evaluate.probe_clips=1", "model.evaluate.probe_steps=1", "model.sampler.steps=1"])


@BENCHMARK_SCRIPT
def test_gaia2_agent_guidance_splits_iou_inside_and_outside_the_boxes(tmp_path) -> None:
    """benchmarks/gaia2_agent_guidance.py: the evaluation's agent table alone, with the IoU inside the conditioning
    boxes and the agent share outside them for every row, the guided rows paired to plain CFG; refuses scale 0."""
    module = load_benchmark("gaia2_agent_guidance")
    tiny = ["model.evaluate.contexts=2", "model.evaluate.probe_clips=2", "model.evaluate.probe_steps=2",
            "model.sampler.steps=2", "model.steps=3"]
    result = module.main(["--out", str(tmp_path), *tiny])
    rows = result["agents"]["rows"]
    assert len(rows) == 8 and result["cameras"] == ["front", "front_left", "front_right"]
    for name, row in rows.items():
        assert 0 <= row["iou_inside_boxes"] <= 1 and 0 <= row["agent_share_outside_boxes"] <= 1
        assert ("iou_inside_boxes_minus_plain" in row) == name.startswith("model, selective CFG")
    table = (tmp_path / "agent_guidance.md").read_text()
    assert "agent share outside the boxes" in table and table.count("| model, selective CFG ×3") == 3
    with pytest.raises(ValueError, match="cfg_scale=0"):
        module.main([*tiny, "model.evaluate.cfg_scale=0"])


def test_agent_table_guided_variants_pick_rows_and_keep_plain_cfg_as_reference(tmp_path) -> None:
    """`--variants` of benchmarks/gaia2_agent_guidance.py (guided_rows): the chosen selective rows beside plain CFG,
    which always runs as their reference; an unknown variant is named in the error; `--guided-only` leaves out the
    unguided model rows."""
    rows = gaia2_evaluate.guided_rows(16, ["full"])
    assert list(rows) == ["model, plain CFG ×16", "model, selective CFG ×16, full second pass"]
    assert [(g.scale, g.spatial, g.spatial_pass) for g in rows.values()] == [(16, False, "agent_tokens"),
                                                                             (16, True, "full")]
    assert len(gaia2_evaluate.guided_rows(3)) == 4
    with pytest.raises(ValueError, match=r"\['dual'\]"):
        gaia2_evaluate.guided_rows(3, ["dual"])
    module = load_benchmark("gaia2_agent_guidance")
    result = module.main(["--variants", "full", "--guided-only", "--", "model.evaluate.contexts=2",
                          "model.evaluate.probe_clips=2", "model.evaluate.probe_steps=2", "model.sampler.steps=2"])
    assert list(result["agents"]["rows"]) == ["real frames", "tokenized real", "model, plain CFG ×3",
                                              "model, selective CFG ×3, full second pass"]
    assert "iou_agent_masks_minus_plain" in result["agents"]["rows"]["model, selective CFG ×3, full second pass"]
