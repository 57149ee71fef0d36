"""Hostile-but-realistic inputs (issue: safe by default): each case must fail with a clear error and do no harm.

Checkpoints cannot run code: pickled payloads, `_target_`s that name anything outside the model packages (at any
depth, or dressed up as a gaia_app path), and damaged files are refused with the file's name, and no file appears.
"""

from __future__ import annotations

import pickle
from pathlib import Path

import pytest

from gaia_app.lit.checkpoint import UnsafeCheckpointError, check_checkpoint_file, load_module, read_checkpoint
from gaia_app.tasks.generate import generate
from gaia_app.tasks.train import train
from gaia_app.weights.targets import UnsafeTargetError, check_targets
from tests.conftest import TINY_TOKENIZER, Payload, compose_config, tampered

pytestmark = pytest.mark.usefixtures("one_thread")

TINY = TINY_TOKENIZER


def test_a_pickled_payload_is_refused_and_runs_nothing(genuine: Path, tmp_path: Path) -> None:
    marker = tmp_path / "pwned"
    path = tampered(genuine, tmp_path, lambda c: c.update(extra=Payload(marker)))
    for load in (read_checkpoint, load_module, check_checkpoint_file):
        with pytest.raises(UnsafeCheckpointError, match=rf"checkpoint '{path}' was refused.*unsupported global"):
            load(path)
    assert not marker.exists()


@pytest.mark.parametrize("where", ["shallow", "nested", "torch_load", "disguised"])
def test_model_config_targets_outside_the_model_packages_are_refused(genuine: Path, tmp_path: Path, where: str) -> None:
    marker = tmp_path / "pwned"
    evil = {"shallow": {"_target_": "pathlib.Path.touch", "self": str(marker)},
            "nested": {"_target_": "pathlib.Path.write_text", "self": str(marker), "data": "x"},
            "torch_load": {"_target_": "torch.load", "f": str(genuine), "weights_only": False},
            "disguised": {"_target_": "gaia_app.models.gaia1.tokenizer.torch.load", "f": str(genuine)}}[where]

    def edit(checkpoint: dict) -> None:
        model_cfg = checkpoint["hyper_parameters"]["model_cfg"]
        if where == "shallow":
            checkpoint["hyper_parameters"]["model_cfg"] = evil
        else:  # deep inside an otherwise genuine config: the net factory's keyword arguments
            model_cfg["net"]["extra"] = [{"inner": evil}]

    path = tampered(genuine, tmp_path, edit)
    with pytest.raises(UnsafeTargetError, match=rf"checkpoint '{path}': hyper_parameters\.model_cfg.*is refused"):
        load_module(path)
    cfg = compose_config("generate", ["mode=reconstruct", f"ckpt={path}", "data=synthetic_frames_tiny",
                                      "extras.print_config=false"], tmp_path / "gen")
    with pytest.raises(UnsafeTargetError):
        generate(cfg)
    assert not marker.exists()


def test_a_genuine_checkpoint_still_loads(genuine: Path) -> None:
    module = load_module(genuine)
    assert type(module).__name__ == "ImageTokenizerModule" and not module.training


@pytest.mark.parametrize("content", [b"", b"PK\x03\x04 truncated zip", b"\x80\x04not a checkpoint"])
def test_empty_or_truncated_checkpoints_name_the_file(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "broken.ckpt"
    path.write_bytes(content)
    with pytest.raises(ValueError, match=rf"checkpoint '{path}' is empty, truncated or not a PyTorch checkpoint"):
        read_checkpoint(path)


def test_a_truncated_copy_of_a_real_checkpoint_names_the_file(genuine: Path, tmp_path: Path) -> None:
    path = tmp_path / "half.ckpt"
    path.write_bytes(genuine.read_bytes()[: genuine.stat().st_size // 2])
    with pytest.raises(ValueError, match=rf"checkpoint '{path}' is empty, truncated"):
        load_module(path)


def test_resuming_from_a_hostile_checkpoint_is_refused_before_lightning_reads_it(genuine: Path, tmp_path: Path) -> None:
    marker = tmp_path / "pwned"
    run_dir = tmp_path / "run"
    (run_dir / "checkpoints").mkdir(parents=True)
    evil = tampered(genuine, tmp_path, lambda c: c.update(extra=Payload(marker)))
    evil.rename(run_dir / "checkpoints" / "last.ckpt")
    cfg = compose_config("train", [*TINY, "trainer.max_steps=3", "ckpt_path=last"], run_dir)
    with pytest.raises(UnsafeCheckpointError, match="last.ckpt' was refused"):
        train(cfg)
    assert not marker.exists()


def test_target_checks_cover_lists_and_allow_the_model_packages() -> None:
    check_targets({"_target_": "gaia_app.lit.gaia1_tokenizer.ImageTokenizerModule",
                   "optim": {"_target_": "torch.optim.AdamW", "_partial_": True},
                   "sched": {"_target_": "gaia_app.lit.schedules.warmup_cosine"}}, "cfg")
    for target in ("os.system", "gaia_app.utils.run_dir.atomic_write_text", "builtins.eval",
                   "gaia_app.nn.no_such_thing", 42):
        with pytest.raises(UnsafeTargetError, match=r"cfg\.a\[1\]\._target_"):
            check_targets({"a": [{}, {"_target_": target}]}, "cfg")


def test_the_sharded_index_is_unpickled_safely(tmp_path: Path) -> None:
    marker = tmp_path / "pwned"
    folder = tmp_path / "sharded.ckpt"
    folder.mkdir()
    (folder / ".metadata").write_bytes(pickle.dumps(Payload(marker)))
    with pytest.raises(UnsafeCheckpointError, match=r"\.metadata' was refused.*Unsupported global: pathlib.Path.touch"):
        check_checkpoint_file(folder)
    assert not marker.exists()


# ---------------------------------------------------------------- names that cannot escape

ESCAPE = "x/../../../../elsewhere/TRAV"


@pytest.fixture(scope="module")
def clip_root(tmp_path_factory) -> Path:
    """Three real clip folders of the synthetic world (16 frames, 64×112)."""
    from gaia_app.data.clip_writer import write_clip
    from gaia_app.data.synthetic import SyntheticClipDataset

    root = tmp_path_factory.mktemp("clips") / "root"
    world = SyntheticClipDataset(num_clips=3, seed=3, clip_len=16)
    for i in range(3):
        write_clip(world[i], root)
    return root


def escaping_copy(clip_root: Path, tmp_path: Path) -> Path:
    """The clip folders with the first clip's camera renamed to ESCAPE in meta.json (its mp4 placed where that name
    points, so only the name check can stop the read)."""
    import json
    import shutil

    root = tmp_path / "inside" / "clips"
    shutil.copytree(clip_root, root)
    clip = sorted(p for p in root.iterdir() if p.is_dir())[0]
    meta = json.loads((clip / "meta.json").read_text())
    for camera in meta.get("cameras") or []:
        camera["name"] = ESCAPE
    meta["camera_names"] = [ESCAPE]
    (clip / "meta.json").write_text(json.dumps(meta))
    target = clip / f"{ESCAPE}.mp4"
    target.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(clip / "front.mp4", target)
    return root


def test_a_camera_name_that_escapes_is_refused_when_read(clip_root: Path, tmp_path: Path) -> None:
    from gaia_app.data.clip import ClipError
    from gaia_app.data.clip_folder import ClipFolderDataset, read_clip

    root = escaping_copy(clip_root, tmp_path)
    bad = sorted(p for p in root.iterdir() if p.is_dir())[0]
    with pytest.raises(ClipError, match=r"meta.json: cameras\[0\].name: camera name 'x/\.\./.*' is not a plain name"):
        read_clip(bad)
    dataset = ClipFolderDataset(root)  # skipped with its reason, the good clip stays
    assert len(dataset) == 2 and "not a plain name" in dataset.skipped[0][1]


@pytest.mark.parametrize("mode", ["tokenize", "reconstruct"])
def test_generate_never_writes_outside_its_folders(genuine: Path, clip_root: Path, tmp_path: Path, mode: str) -> None:
    root = escaping_copy(clip_root, tmp_path)
    before = {p for p in tmp_path.rglob("*")}
    out = tmp_path / "inside" / "out"
    cfg = compose_config("generate", [f"mode={mode}", f"ckpt={genuine}", "data=video_folder",
                                      f"data.source.root={root}", "data.height=64", "data.width=112", "data.clip_len=8",
                                      "data.fps=null", "data.num_workers=0",
                                      f"out_dir={out}", "extras.print_config=false"], out / "run")
    generate(cfg)  # the escaping clip is skipped at setup (with its reason), the other one is processed
    written = {p for p in tmp_path.rglob("*")} - before
    outside = [p for p in written if tmp_path / "inside" not in p.parents]
    assert not outside, outside


def test_the_dashcam_importer_refuses_a_camera_that_escapes(clip_root: Path, tmp_path: Path) -> None:
    from gaia_app.data.clip import ClipError
    from gaia_app.data.importers.dashcam import import_dashcam

    video = sorted(clip_root.rglob("front.mp4"))[0]
    out = tmp_path / "inside"
    with pytest.raises(ClipError, match=r"--camera: camera name '\.\./\.\./cam' is not a plain name"):
        import_dashcam(video, out, camera="../../cam", progress=False)
    with pytest.raises(ClipError, match="--clip-id"):
        import_dashcam(video, out, clip_id="../up", progress=False)
    assert not [p for p in tmp_path.rglob("*") if p.is_file()]


def test_output_paths_stay_under_their_root(tmp_path: Path) -> None:
    from gaia_app.data.clip import ClipError
    from gaia_app.data.names import check_camera_name, check_clip_id, inside

    assert inside(tmp_path, "a", "b.npy") == (tmp_path / "a" / "b.npy").resolve()
    for parts in (("..", "x"), ("a/../../x",), ("/etc/passwd",), (".",)):
        with pytest.raises(ClipError, match="would leave its folder"):
            inside(tmp_path, *parts)
    for name in ("", ".hidden", "a/b", "a\\b", "..", "a..b", "x" * 200):
        with pytest.raises(ClipError, match="clip id"):
            check_clip_id(name, "test")
    for name in ("front.left", "front left", "../cam", "", None):
        with pytest.raises(ClipError, match="camera name"):
            check_camera_name(name, "test")
    assert check_clip_id("drive_2024.01.05-a", "t") and check_camera_name("CAM_FRONT-left", "t")


# ---------------------------------------------------------------- caches that know what they hold


def test_token_cache_files_of_two_clips_cannot_collide(tmp_path: Path) -> None:
    import numpy as np

    from gaia_app.data.clip import Clip
    from gaia_app.data.token_cache import TokenSegment, find_segments, write_segment
    from gaia_app.pipelines.gaia1_tokenizer import segment_names

    def clip(clip_id: str, camera: str) -> Clip:
        return Clip(frames=np.zeros((1, 2, 3, 8, 8), np.uint8), timestamps=np.arange(2.0), clip_id=clip_id,
                    meta={"camera_names": [camera]})

    names = segment_names(clip("drive", "front_left")) + segment_names(clip("drive_front", "left"))
    for k, name in enumerate(names):
        write_segment(tmp_path, TokenSegment(name, np.full((2, 4), k), None))
    files = find_segments(tmp_path)
    assert len(files) == 2 and sorted(int(np.load(f)[0, 0]) for f in files) == [0, 1]


def test_tokenize_refuses_a_cache_made_differently_unless_overwritten(genuine: Path, tmp_path: Path) -> None:
    from gaia_app.data.clip import ClipError

    out = tmp_path / "cache"
    base = ["mode=tokenize", f"ckpt={genuine}", "data=synthetic_tiny", "splits=[train]", "max_clips=2",
            f"out_dir={out}", "extras.print_config=false"]
    generate(compose_config("generate", base, tmp_path / "g1"))
    with pytest.raises(ClipError,
                       match=r"holds a cache made differently \(fps: cache has None, this run makes 12\.5\)"):
        generate(compose_config("generate", [*base, "fps=12.5"], tmp_path / "g2"))
    results = generate(compose_config("generate", [*base, "fps=12.5", "overwrite=true"], tmp_path / "g3"))["results"]
    assert results["train"]["written"] == 2 and results["train"]["skipped"] == 0
    (out / "train" / "cache.json").unlink()  # a cache from before manifests: what made it is unknown
    with pytest.raises(ClipError, match="holds files but no cache.json"):
        generate(compose_config("generate", base, tmp_path / "g4"))


# ---------------------------------------------------------------- ranges and errors that name the setting


@pytest.mark.parametrize(("seconds", "ok"), [(0, False), (-1, False), (float("nan"), False), ("abc", False),
                                              (0.1, True)])
def test_seconds_of_future_must_be_positive(seconds, ok: bool) -> None:
    from gaia_app.pipelines.gaia1_inputs import future_frames

    if ok:
        assert future_frames(seconds, 6.25) == 1
    else:
        with pytest.raises(ValueError, match=r"seconds=.*expected a positive number of seconds"):
            future_frames(seconds, 6.25)


@pytest.mark.parametrize(("speed", "curvature", "match"), [
    (1e39, None, r"speed=1e\+39: every commanded value must be a finite number in \[0, 70\] m/s"),
    (float("nan"), None, r"speed=nan: every commanded value must be a finite number"),
    (-3.0, None, r"speed=-3.0: .*\[0, 70\]"),
    ([5.0, float("inf")], None, r"speed: 2 values for 4 future steps"),
    (None, 2.0, r"curvature=2.0: .*\[-0.5, 0.5\] 1/m"),
    ("fast", None, r"speed='fast': expected one of \['accelerate', 'brake', 'keep'\]"),
])
def test_commanded_numbers_are_range_checked(speed, curvature, match: str) -> None:
    from gaia_app.pipelines.gaia1_inputs import future_actions

    with pytest.raises(ValueError, match=match):
        future_actions(speed, curvature, frames=4, rate=6.25, start_speed=10.0)
    assert future_actions(12.0, -0.02, frames=4, rate=6.25, start_speed=10.0).shape == (4, 2)


def test_generate_refuses_zero_seconds_and_absurd_speeds(tmp_path: Path) -> None:
    cfg = compose_config("generate", ["mode=action", "weights=gaia1", "speed=1e39", "seconds=0.5",
                                      "extras.print_config=false"], tmp_path / "a")
    with pytest.raises(ValueError, match=r"speed=1e\+39"):
        generate(cfg)
    cfg = compose_config("generate", ["mode=video", "weights=gaia1", "seconds=0", "extras.print_config=false"],
                         tmp_path / "b")
    with pytest.raises(ValueError, match=r"seconds=0: expected a finite number in \(0, 120\]"):
        generate(cfg)


def test_label_speeds_outside_the_physical_range_are_refused() -> None:
    import numpy as np

    from gaia_app.data.actions import actions_from_labels
    from gaia_app.data.clip import ClipError

    columns = {"speed": np.array([10.0, 1e9, 10.0]), "curvature": np.zeros(3)}
    with pytest.raises(ClipError, match=r"labels.jsonl: speed 1e\+09 at frame 1 is outside \[-100, 100\] m/s"):
        actions_from_labels(columns, where="labels.jsonl")
    columns = {"speed": np.full(3, 10.0), "curvature": np.array([0.0, 0.0, -5.0])}
    with pytest.raises(ClipError, match=r"curvature -5 at frame 2 is outside \[-1, 1\] 1/m"):
        actions_from_labels(columns, where="labels.jsonl")


@pytest.mark.parametrize(("override", "match"), [
    ("data.batch_size=abc", r"data.batch_size='abc': expected an integer ≥ 1"),
    ("data.batch_size=0", r"data.batch_size=0: expected an integer ≥ 1"),
    ("data.num_workers=-1", r"data.num_workers=-1: expected an integer ≥ 0"),
])
def test_loader_settings_are_checked_when_built(override: str, match: str, tmp_path: Path) -> None:
    from gaia_app.tasks.train import build

    cfg = compose_config("train", [*TINY, override], tmp_path)
    with pytest.raises(Exception, match=match):
        build(cfg)


def test_a_setting_of_another_data_config_is_named(clip_root: Path, tmp_path: Path) -> None:
    from gaia_app.tasks.train import build

    cfg = compose_config("train", ["experiment=gaia1/video_decoder_tiny", "data=video_folder",
                                   f"data.source.root={clip_root}", "extras.print_config=false"], tmp_path)
    with pytest.raises(ValueError, match=r"^data.source.clip_len: gaia_app.data.clip_folder.ClipFolderDataset takes "
                                         r"no 'clip_len'.*remove it with ~data.source.clip_len$"):
        build(cfg)


def test_clips_shorter_than_one_window_are_skipped_at_setup_with_a_count(clip_root: Path, tmp_path: Path,
                                                                         caplog) -> None:
    import json
    import logging
    import shutil

    from gaia_app.data.clip import ClipError
    from gaia_app.data.clip_folder import ClipFolderDataset
    from gaia_app.data.datamodules import ClipDataModule

    root = tmp_path / "clips"
    shutil.copytree(clip_root, root)
    short = sorted(p for p in root.iterdir() if p.is_dir())[0]
    labels = (short / "labels.jsonl").read_text().splitlines()[:5]  # 5 of 16 frames labelled: 5 frames at 25 Hz
    (short / "labels.jsonl").write_text("\n".join(labels) + "\n")
    from gaia_app.data.clip_folder import read_clip
    from gaia_app.data.clip_writer import write_clip  # a consistent short clip: rewrite it from its first 5 frames

    clip = read_clip(sorted(p for p in clip_root.iterdir() if p.is_dir())[0], max_frames=5)
    write_clip(clip, root, overwrite=True)
    dm = ClipDataModule(ClipFolderDataset(root), val_source=ClipFolderDataset(root), clip_len=8, fps=None,
                        batch_size=1)
    with caplog.at_level(logging.WARNING):
        dm.setup()
    assert dm.skipped_short == 2 and len(dm.train_clips) == 2  # one short clip, in the train and the val source
    assert "skipped 1 of 3 clips with fewer than data.clip_len=8 frames" in caplog.text
    assert next(iter(dm.train_dataloader()))["video"].shape[2] == 8
    with pytest.raises(ClipError, match=r"data.source: none of its 3 clips has data.clip_len=99 frames"):
        ClipDataModule(ClipFolderDataset(root), clip_len=99, batch_size=1).setup()
    del json
