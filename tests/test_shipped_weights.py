"""Shipped weights (gaia_app/weights/folders.py): export from checkpoints, rebuild from .safetensors + .yaml alone,
generate with `weights=`, and clear errors for missing, corrupt or foreign files."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import yaml
from rerun.chunk import RrdReader

from gaia_app.data.video_io import video_info
from gaia_app.eval.controllability import save_probes
from gaia_app.models.probes import InverseDynamicsProbe, SceneAttributeProbe
from gaia_app.pipelines.gaia1 import Gaia1Pipeline
from gaia_app.tasks.generate import generate
from gaia_app.weights.folders import WEIGHTS_ROOT, load_nets, shipped_folder
from tests.conftest import compose_config
from tests.test_generate_rollouts import SIZE, checkpoints, run  # noqa: F401  (checkpoints is a fixture)


@pytest.fixture(scope="module")
def shipped(checkpoints, tmp_path_factory) -> Path:  # noqa: F811
    """A weights folder exported from the tiny checkpoints, with (untrained) probes for 32×48 at 6.25 Hz."""
    root = tmp_path_factory.mktemp("shipped")
    save_probes(root / "probes", InverseDynamicsProbe(), SceneAttributeProbe(), {"image_size": [32, 48], "rate": 6.25})
    ckpts = {k: v for k, v in checkpoints.items() if k != "decoder_ckpt"}
    results = run(ckpts, root / "export", "mode=export", f"out_dir={root / 'weights'}",
                  f"controllability.probes={root / 'probes'}", decoder=False)
    assert results["world_model"]["bytes"] > 0 and results["probes"] == str(root / "weights" / "probes")
    return root / "weights"


def test_weights_rebuild_the_nets_of_the_checkpoints(checkpoints, shipped: Path) -> None:  # noqa: F811
    trained = Gaia1Pipeline.from_checkpoints(checkpoints["tokenizer_ckpt"], checkpoints["world_model_ckpt"],
                                             image_size=(32, 48))
    rebuilt = Gaia1Pipeline.from_weights(shipped)
    assert rebuilt.image_size == (32, 48) and rebuilt.rate == 6.25 and rebuilt.decoder is None
    for a, b in ((trained.world_model, rebuilt.world_model), (trained.tokenizer, rebuilt.tokenizer)):
        for (name, x), (_, y) in zip(a.state_dict().items(), b.state_dict().items(), strict=True):
            assert y.dtype == x.dtype, name  # rebuilt in float32 from float16 storage
            torch.testing.assert_close(y, x.to(torch.float16).to(x.dtype), msg=name)
    frames = torch.rand(4, 3, 32, 48, generator=torch.Generator().manual_seed(0)) * 2 - 1
    with torch.no_grad():
        same = (rebuilt.tokenizer.encode(frames) == trained.tokenizer.encode(frames)).float().mean()
        decoded = rebuilt.tokenizer.decode(trained.tokenizer.encode(frames))
        torch.testing.assert_close(decoded, trained.tokenizer.decode(trained.tokenizer.encode(frames)),
                                   atol=2e-2, rtol=0)
    assert same > 0.95  # float16 storage may flip a near tie between two codes, rarely
    captions = [["It is night."] * 2]
    torch.testing.assert_close(rebuilt.text_encoder(captions), trained.text_encoder(captions), atol=1e-3, rtol=1e-3)


def test_generation_and_controllability_run_from_weights_alone(shipped: Path, tmp_path: Path) -> None:
    cfg = compose_config("generate", ["mode=action", f"weights={shipped}", "speed=brake", "curvature=left",
                                      "num_futures=1", "seconds=0.5", "extras.print_config=false", *SIZE],
                         tmp_path / "a")
    results = generate(cfg)["results"]
    assert (tmp_path / "a" / "grid.mp4").is_file() and results["fps"] == 6.25
    args = ["mode=controllability", f"weights={shipped}", "seconds=0.5", "controllability.contexts=2",
            "controllability.commands=[[brake,left],[keep,right]]", "controllability.prompts.time_of_day=[night]",
            "~controllability.prompts.weather", "controllability.text_repeats=1", "controllability.floor_repeats=1",
            "controllability.real_clips=3",
            "extras.print_config=false", *SIZE]
    results = generate(compose_config("generate", args, tmp_path / "c"))["results"]
    assert results["probes"]["image_size"] == [32, 48]  # the shipped probes, not retrained ones
    assert not (tmp_path / "c" / "probes").exists()


def corrupt(folder: Path, name: str) -> None:
    (folder / name).write_bytes(b"not a safetensors file")


def foreign_target(folder: Path, name: str, target: str = "os.system") -> None:
    config = yaml.safe_load((folder / name).read_text())
    config["nets"]["net"]["_target_"] = target
    (folder / name).write_text(yaml.safe_dump(config))


@pytest.mark.parametrize(("damage", "error", "match"), [
    (lambda f: (f / "world_model.safetensors").unlink(), FileNotFoundError,
     r"world_model.safetensors is missing: export it again"),
    (lambda f: corrupt(f, "tokenizer.safetensors"), ValueError, r"tokenizer.safetensors: not a readable safetensors"),
    (lambda f: foreign_target(f, "tokenizer.yaml"), ValueError, r"nets.net._target_: _target_ 'os.system' is refused"),
    # starts like a gaia_app net but resolves to torch.load
    (lambda f: foreign_target(f, "tokenizer.yaml", "gaia_app.models.gaia1.tokenizer.torch.load"), ValueError,
     r"is refused.*resolves to torch.serialization.load.*export it again"),
    (lambda f: (f / "tokenizer.yaml").write_text("format: 7\n"), ValueError,
     r"tokenizer.yaml: expected a weights config"),
])
def test_damaged_weights_are_named_with_how_to_restore_them(shipped: Path, tmp_path: Path, damage, error,
                                                            match) -> None:
    folder = tmp_path / "weights"
    shutil.copytree(shipped, folder)
    damage(folder)
    with pytest.raises(error, match=match):
        Gaia1Pipeline.from_weights(folder)


def test_inside_the_package_the_hint_says_how_to_restore(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"git checkout -- gaia_app/weights.*make reproduce"):
        load_nets(WEIGHTS_ROOT / "no_such_family", "tokenizer")
    with pytest.raises(FileNotFoundError, match=r"weights=nonexistent: no such folder"):
        shipped_folder("nonexistent")


def test_weights_and_checkpoints_together_are_refused(checkpoints, shipped: Path, tmp_path: Path) -> None:  # noqa: F811
    with pytest.raises(ValueError, match="replaces the checkpoints; drop tokenizer_ckpt"):
        run({"tokenizer_ckpt": checkpoints["tokenizer_ckpt"]}, tmp_path, "mode=video", f"weights={shipped}",
            decoder=False)


def test_cross_entropy_report_scores_every_mode_against_the_baselines(checkpoints, tmp_path: Path) -> None:  # noqa: F811
    from gaia_app.protocols.world_model_report import main

    tokens = Path(checkpoints["world_model_ckpt"]).parents[2] / "tokens"
    main(["--ckpt", str(checkpoints["world_model_ckpt"]), "--tokens", str(tokens), "--out", str(tmp_path)])
    results = json.loads((tmp_path / "cross_entropy.json").read_text())
    assert set(results["model"]) == {"unconditional", "actions", "text"} and results["windows"] > 0
    for estimate in (*results["model"].values(), results["action_gain"]):
        assert estimate["low"] <= estimate["mean"] <= estimate["high"]
    assert 0 < results["copy_previous"] and 0 < results["unigram"] <= math.log(512) + 1e-6
    assert "| copy previous frame" in (tmp_path / "cross_entropy.md").read_text()


def test_reproduce_lists_every_step_of_the_recipe(capsys) -> None:
    from gaia_app.tasks.reproduce import main

    main(["--dry-run", "--out", "outputs/reference"])
    commands = capsys.readouterr().out.strip().splitlines()
    assert [c.split()[1] for c in commands] == ["train.py", "generate.py", "train.py", "generate.py", "train.py", "-m",
                                                "benchmarks/probe_quality.py", "generate.py", "train.py", "generate.py"]
    assert "experiment=gaia1/reference/tokenizer" in commands[0]
    assert "experiment=gaia1/reference/world_model" in commands[2]
    assert "data.source.driven_share=1.0" in commands[3] and "seed=5" in commands[3]
    assert "experiment=gaia1/reference/world_model_finetune" in commands[4]
    assert "model.init_from=outputs/reference/world_model/checkpoints/last.ckpt" in commands[4]
    assert all("world_model_ckpt=outputs/reference/world_model_finetune/" in c for c in (commands[7], commands[-1]))
    assert "mode=export" in commands[-1] and "out_dir=gaia_app/weights/gaia1" in commands[-1]
    assert "experiment=gaia1/reference/video_decoder" in commands[-2] and "decoder_ckpt=" in commands[-1]


def test_reproduce_gpu_adds_the_gpu_and_less_snow_fine_tunes_whose_model_the_later_steps_use(capsys) -> None:
    from gaia_app.tasks.reproduce import main

    main(["--dry-run", "--gpu", "--out", "outputs/reference"])
    commands = capsys.readouterr().out.strip().splitlines()
    assert len(commands) == 15
    tokenize, more, train, tokenize_less_snow, train_less_snow = commands[5:10]
    assert all("device=cuda" in c and "out_dir=outputs/reference/tokens_gpu" in c for c in (tokenize, more))
    assert "seed=5" in tokenize and "seed=6" in more and "data.source.num_clips=2366" in more
    assert "experiment=gaia1/reference/world_model_finetune_gpu" in train
    assert "model.init_from=outputs/reference/world_model_finetune/checkpoints/last.ckpt" in train
    # the last fine-tune: rendered on the CPU, another world, half the default share of snow
    assert "device=cuda" not in tokenize_less_snow and "seed=8" in tokenize_less_snow
    assert "snow:0.08" in tokenize_less_snow and "out_dir=outputs/reference/tokens_less_snow" in tokenize_less_snow
    assert "experiment=gaia1/reference/world_model_less_snow" in train_less_snow
    assert "model.init_from=outputs/reference/world_model_gpu/checkpoints/last.ckpt" in train_less_snow
    assert all("outputs/reference/world_model_less_snow/checkpoints/last.ckpt" in c
               for c in (commands[10], commands[-1]))


def test_reproduce_until_stops_after_the_step_and_resumes_past_recorded_steps(tmp_path: Path, monkeypatch,
                                                                              capsys) -> None:
    from gaia_app.tasks import reproduce

    ran = []
    monkeypatch.setattr(reproduce, "run_step", lambda name, command: ran.append(name) or {"step": name, "wall_s": 1.0})
    out = tmp_path / "reference"
    out.mkdir()
    reproduce.main(["--out", str(out), "--weights", str(tmp_path / "weights"), "--until", "tokenize"])
    assert ran == ["tokenizer", "tokenize"] and "stopped after tokenize" in capsys.readouterr().out
    assert [r["step"] for r in json.loads((out / "reproduce.json").read_text())] == ["tokenizer", "tokenize"]
    assert not (tmp_path / "MANIFEST.md").exists()
    reproduce.main(["--out", str(out), "--weights", str(tmp_path / "weights"), "--until", "world_model"])
    assert ran == ["tokenizer", "tokenize", "world_model"]  # the recorded steps are not run again
    # a later step recorded earlier (e.g. the probes, which need no model) survives a run that stops before it
    records = json.loads((out / "reproduce.json").read_text())
    (out / "reproduce.json").write_text(json.dumps([*records, {"step": "probes", "wall_s": 2.0}]))
    reproduce.main(["--out", str(out), "--weights", str(tmp_path / "weights"), "--until", "cross_entropy"])
    assert ran[-1] == "cross_entropy" and "probes" not in ran
    assert [r["step"] for r in json.loads((out / "reproduce.json").read_text())] == [
        "tokenizer", "tokenize", "world_model", "tokenize_finetune", "world_model_finetune", "cross_entropy", "probes"]


def test_showcase_steers_one_context_four_ways_and_prompts_against_none(shipped: Path, tmp_path: Path) -> None:
    cfg = compose_config("generate", ["mode=showcase", f"weights={shipped}", "context.frames=2", "seconds=0.5",
                                      "extras.print_config=false", *SIZE], tmp_path)
    results = generate(cfg)["results"]
    assert results["commands"] == ["brake / straight", "accelerate / straight", "keep / left", "keep / right"]
    commanded = np.array(results["commanded_actions"])  # (4 commands, 2 context + 4 generated, 2)
    assert commanded.shape == (4, 6, 2)
    assert commanded[0, -1, 0] < commanded[0, 2, 0] and commanded[1, -1, 0] > commanded[1, 2, 0]  # brake, accelerate
    assert commanded[2, 2:, 1].min() > 0 > commanded[3, 2:, 1].max()  # left, right
    for panel, rows in (("commands", 6), ("prompts", 3)):  # commands: the real continuation raw and tokenized
        assert video_info(tmp_path / panel / "grid.mp4").num_frames == (6 if panel == "commands" else 4)
        png = cv2.imread(str(tmp_path / panel / "strip.png"))
        assert png.shape[0] == rows * 32 * 2  # one row per video, upscaled 2×
    chunks = RrdReader(str(tmp_path / "showcase.rrd")).stream().collect().stream().to_chunks()
    entities = {chunk.entity_path for chunk in chunks}
    assert {"/actions/speed/brake_straight", "/actions/curvature/keep_left", "/commands/real",
            "/commands/real_tokenized", "/prompts/It_is_night"} <= entities
    assert "| brake / straight |" in (tmp_path / "showcase.md").read_text()


def test_a_world_model_trains_on_the_shipped_tokenizer_and_exports_beside_it(checkpoints, shipped: Path,  # noqa: F811
                                                                              tmp_path: Path) -> None:
    """mode=tokenize weights= makes a token cache with a weights folder's tokenizer; mode=export weights= then
    writes a folder with that tokenizer (copied unchanged), the new world model and the folder's probes."""
    from gaia_app.data.token_cache import find_segments

    out = tmp_path / "tokens"
    cfg = compose_config("generate", ["mode=tokenize", f"weights={shipped}", "data=synthetic_tiny", "splits=[train]",
                                      "max_clips=2", *SIZE, f"out_dir={out}", "extras.print_config=false"],
                         tmp_path / "t")
    assert generate(cfg)["results"]["train"]["written"] == 2
    tokens = np.load(find_segments(out / "train")[0])
    assert tokens.shape[1:] == (8, 12)  # the shipped tokenizer's grid at 32×48
    cfg = compose_config("generate", ["mode=reconstruct", f"weights={shipped}", "data=synthetic_tiny", "num_clips=1",
                                      *SIZE, "extras.print_config=false"], tmp_path / "r")
    reconstructed = generate(cfg)["results"]
    assert len(reconstructed) == 1 and 0 < next(iter(reconstructed.values()))["psnr"] < 100  # a tiny test tokenizer
    assert list((tmp_path / "r").glob("*.mp4")) and (tmp_path / "r" / "reconstruction.rrd").is_file()
    with pytest.raises(ValueError, match=r"trained on \(32, 48\) frames, but data.height × data.width is \(64, 112\)"):
        generate(compose_config("generate", ["mode=tokenize", f"weights={shipped}", "data=synthetic_tiny",
                                             f"out_dir={tmp_path / 'x'}", "extras.print_config=false"], tmp_path / "x"))
    results = run({"world_model_ckpt": checkpoints["world_model_ckpt"]}, tmp_path / "e", "mode=export",
                  f"weights={shipped}", f"out_dir={tmp_path / 'mine'}", decoder=False)
    assert results["tokenizer"].startswith("copied from")
    for name in ("tokenizer.safetensors", "tokenizer.yaml", "probes/probes.safetensors"):
        assert (tmp_path / "mine" / name).read_bytes() == (shipped / name).read_bytes()
    Gaia1Pipeline.from_weights(tmp_path / "mine")


def test_generation_from_checkpoints_builds_no_lightning_module(checkpoints, monkeypatch) -> None:  # noqa: F811
    """Gaia1Pipeline.from_checkpoints builds the nets from each checkpoint's checked config and tensors alone
    (weights/nets.py): the LightningModules, their objectives and loss networks are never built."""
    from gaia_app.lit.base import GaiaModule

    def refuse(*args, **kwargs):
        raise AssertionError("a LightningModule was built for inference")

    monkeypatch.setattr(GaiaModule, "__init__", refuse)
    pipeline = Gaia1Pipeline.from_checkpoints(checkpoints["tokenizer_ckpt"], checkpoints["world_model_ckpt"],
                                              checkpoints["decoder_ckpt"], decoder_steps=2)
    assert pipeline.decoder is not None and pipeline.image_size == (32, 48)
    assert not pipeline.world_model.training and not pipeline.decoder.net.training


def test_weights_with_a_video_decoder_decode_with_its_ema_weights(checkpoints, tmp_path: Path) -> None:  # noqa: F811
    """mode=export with decoder_ckpt= adds video_decoder.{safetensors,yaml} (the EMA weights); weights= runs decode
    with it unless video_decoder=false, and the controllability protocol never does."""
    from gaia_app.protocols.loading import load_pipeline

    results = run(checkpoints, tmp_path / "export", "mode=export", f"out_dir={tmp_path / 'weights'}")
    assert results["video_decoder"]["bytes"] > 0
    folder = tmp_path / "weights"
    info = yaml.safe_load((folder / "video_decoder.yaml").read_text())["info"]
    # run() passes decoder_steps=1: the export records the decoding setting it was given
    assert info == {"frames": 7, "context_frames": 2, "timesteps": 1000, "sampler": "ddim", "steps": 1}
    trained = Gaia1Pipeline.from_checkpoints(*(checkpoints[k] for k in ("tokenizer_ckpt", "world_model_ckpt",
                                                                         "decoder_ckpt")), decoder_steps=2)
    rebuilt = Gaia1Pipeline.from_weights(folder, decoder_steps=2)
    for (name, x), (_, y) in zip(trained.decoder.net.state_dict().items(), rebuilt.decoder.net.state_dict().items(),
                                 strict=True):
        torch.testing.assert_close(y, x.to(torch.float16).to(x.dtype), msg=name)
    tokens = torch.randint(0, 512, (1, 7, 8, 12), generator=torch.Generator().manual_seed(0))
    decoded = [pipe.decoder.decode(tokens, torch.Generator().manual_seed(0)) for pipe in (trained, rebuilt)]
    torch.testing.assert_close(decoded[1], decoded[0], atol=5e-2, rtol=0)
    assert Gaia1Pipeline.from_weights(folder, video_decoder=False).decoder is None
    cfg = compose_config("generate", [f"weights={folder}", "video_decoder=false", "extras.print_config=false", *SIZE],
                         tmp_path / "run")
    assert load_pipeline(cfg).decoder is None and load_pipeline(cfg, video_decoder=True).decoder is not None
    # the decoding setting recorded at export is what weights= runs use unless told otherwise
    run(checkpoints, tmp_path / "export_mean", "mode=export", f"out_dir={tmp_path / 'mean'}",
        "decoder_sampler=one_step_mean", "decoder_steps=3")
    assert yaml.safe_load((tmp_path / "mean" / "video_decoder.yaml").read_text())["info"]["sampler"] == "one_step_mean"
    sampler = Gaia1Pipeline.from_weights(tmp_path / "mean").decoder.sampler
    assert type(sampler).__name__ == "OneStepMeanSampler" and sampler.draws == 3
    assert Gaia1Pipeline.from_weights(tmp_path / "mean", decoder_sampler="ddim").decoder.sampler.steps == 3


def test_floor_calibration_reads_real_clips_and_each_picker(shipped: Path, tmp_path: Path, monkeypatch) -> None:
    """benchmarks/floor_calibration.py: the probe's reading of real clips and of unprompted rollouts per picker."""
    import json
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import floor_calibration

    monkeypatch.setattr(sys, "argv", ["floor_calibration.py", f"--weights={shipped}", "--rollouts=3", "--batch=2",
                                      "--real-clips=2", "--seconds=0.5", "--pickers=top_k,top_p", f"--out={tmp_path}"])
    floor_calibration.main()
    results = json.loads((tmp_path / "results.json").read_text())
    assert list(results["rows"]) == ["real clips (default mix)", "real clips through the tokenizer", "top_k k=50",
                                     "top_p p=0.9"]
    assert results["tv"]["real clips (default mix)"] == {"time_of_day": 0.0, "weather": 0.0}
    night = results["rows"]["top_p p=0.9"]["time_of_day"]["night"]
    assert 0 <= night[1] <= night[0] <= night[2] <= 1 and "| top_k k=50 |" in (tmp_path / "results.md").read_text()


@pytest.mark.parametrize("shared", [True, False])
def test_showcase_futures_share_their_noise_when_asked(shipped: Path, tmp_path: Path, shared: bool) -> None:
    """Two identical commands: with showcase.shared_noise their futures are one future; without, two draws."""
    from gaia_app.protocols.loading import load_pipeline
    from gaia_app.tasks.showcase import command_panel

    cfg = compose_config("generate", ["mode=showcase", f"weights={shipped}", "context.frames=2", "seconds=0.5",
                                      "showcase.commands=[[keep,straight],[keep,straight]]",
                                      f"showcase.shared_noise={str(shared).lower()}", *SIZE], tmp_path)
    futures = command_panel(cfg, load_pipeline(cfg), torch.Generator().manual_seed(0))["futures"]
    assert torch.equal(futures[0], futures[1]) == shared


@pytest.mark.parametrize("shared", [True, False])
def test_showcase_prompt_rollouts_share_their_noise_when_asked(shipped: Path, tmp_path: Path, shared: bool) -> None:
    """The same prompt twice: with showcase.shared_noise one rollout; without, two draws. Different prompts (and no
    prompt) from the same noise still differ."""
    from gaia_app.protocols.loading import load_pipeline
    from gaia_app.tasks.showcase import prompt_panel

    cfg = compose_config("generate", ["mode=showcase", f"weights={shipped}", "seconds=0.5",
                                      "showcase.prompts=[It is night.,It is night.,It is snowing.]",
                                      f"showcase.shared_noise={str(shared).lower()}", *SIZE], tmp_path)
    panel = prompt_panel(cfg, load_pipeline(cfg), torch.Generator().manual_seed(0))
    none, night, night_again, snow = panel["futures"]
    assert panel["names"] == ["no prompt", "It is night.", "It is night.", "It is snowing."]
    assert torch.equal(night, night_again) == shared
    assert not torch.equal(night, snow) and not torch.equal(none, night)


@pytest.mark.parametrize("shared", [True, False])
def test_controllability_shares_noise_within_a_context_when_asked(shipped: Path, tmp_path: Path, monkeypatch,
                                                                  shared: bool) -> None:
    """controllability.shared_noise hands the model row one noise group per context (command-major batch)."""
    from gaia_app.protocols import controllability

    groups = []
    original = controllability.rollout_frames

    def recording(*args, **kwargs):
        groups.append(args[7] if len(args) > 7 else kwargs.get("noise_groups"))
        return original(*args, **kwargs)

    monkeypatch.setattr(controllability, "rollout_frames", recording)
    cfg = compose_config("generate", ["mode=controllability", f"weights={shipped}", "seconds=0.5",
                                      "controllability.contexts=2",
                                      "controllability.commands=[[brake,left],[keep,right]]",
                                      f"controllability.shared_noise={str(shared).lower()}", *SIZE], tmp_path)
    pipeline = controllability.load_pipeline(cfg, video_decoder=False)
    probe = controllability.probes_for(cfg, pipeline, 6, tmp_path)[0]
    controllability.action_table(cfg, pipeline, probe, torch.Generator().manual_seed(0))
    model_groups = groups[0]  # the model row rolls out first, then the floor (no actions, no groups)
    assert (model_groups.tolist() == [0, 1, 0, 1]) if shared else model_groups is None
    assert groups[1] is None


@pytest.mark.slow  # a benchmark script end to end on the shipped weights; the quick tier reaches its gaia_app lines
def test_shared_noise_benchmark_scores_both_couplings_per_seed(shipped: Path, tmp_path: Path, monkeypatch) -> None:
    """benchmarks/shared_noise_adherence.py: ceiling, floor, and the model per seed and coupling, paired."""
    import json
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import shared_noise_adherence

    monkeypatch.setattr(sys, "argv", ["shared_noise_adherence.py", f"--weights={shipped}", "--seeds", "1", "2",
                                      f"--out={tmp_path}", "--", "context.frames=2", "seconds=0.5",
                                      "controllability.contexts=2", "token_sampler.progress=false"])
    shared_noise_adherence.main()
    results = json.loads((tmp_path / "results.json").read_text())
    assert list(results["rows"]) == ["ceiling", "floor", "independent, seed 1", "shared, seed 1",
                                     "independent, seed 2", "shared, seed 2"]
    speed = results["summary"]["speed_contrast"]
    assert len(speed["shared"]["per_seed"]) == 2 and speed["floor"] > 0
    assert speed["shared_minus_independent"]["n"] == 2  # paired over the two contexts
    assert "| speed_contrast | shared |" in (tmp_path / "results.md").read_text()
