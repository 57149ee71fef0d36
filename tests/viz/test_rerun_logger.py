"""RerunLogger + RerunMediaCallback: train a tiny module, read the .rrd back, check its content."""

from __future__ import annotations

import argparse
import logging
from collections import defaultdict
from pathlib import Path

import lightning.pytorch as pl
import pytest
import torch
from omegaconf import OmegaConf
from rerun.chunk import RrdReader
from torch.utils.data import DataLoader, TensorDataset

from gaia_app.viz import rerun_logger as rl
from gaia_app.viz import viewer
from gaia_app.viz.callbacks import RerunMediaCallback
from gaia_app.viz.rerun_logger import RerunLogger, flatten_params, rerun_logger_of

T, B = 4, 4  # video frames, batch size


class TinyModule(pl.LightningModule):
    """A linear regression that records its logged losses and exposes `media(batch)`.

    Module-level so that DDP child processes can unpickle it.
    """

    def __init__(self, lr: float = 0.05, width: int = 4) -> None:
        super().__init__()
        self.save_hyperparameters()
        self.net = torch.nn.Linear(width, 1)
        self.logged: list[float] = []

    def training_step(self, batch, batch_idx):
        x, y = batch
        loss = torch.nn.functional.mse_loss(self.net(x), y)
        self.log("train/loss", loss, on_step=True, on_epoch=False)
        self.logged.append(loss.item())
        return loss

    def validation_step(self, batch, batch_idx):
        x, y = batch
        self.log("val/loss", torch.nn.functional.mse_loss(self.net(x), y))

    def media(self, batch) -> dict:
        x, _ = batch
        b = x.shape[0]
        img = torch.linspace(-1, 1, b * 3 * 8 * 8).reshape(b, 3, 8, 8)
        return {
            "val/reconstruction": img,
            "val/rollout": img[:, None].expand(b, T, 3, 8, 8),
            "val/tokens": torch.arange(b * 16).reshape(b, 4, 4) % 16,
            "val/caption": [f"clip {i}" for i in range(b)],
        }

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=self.hparams.lr)


def _loader() -> DataLoader:
    g = torch.Generator().manual_seed(0)
    data = TensorDataset(torch.randn(3 * B, 4, generator=g), torch.randn(3 * B, 1, generator=g))
    return DataLoader(data, batch_size=B)


def _trainer(tmp_path: Path, **kw) -> pl.Trainer:
    return pl.Trainer(
        max_epochs=2,
        limit_train_batches=3,
        limit_val_batches=1,
        log_every_n_steps=1,
        logger=RerunLogger(str(tmp_path)),
        callbacks=[RerunMediaCallback()],
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        accelerator="cpu",
        **kw,
    )


def _read(path: Path):
    """-> reader, {entity: chunks (temporal)}, {entity: chunks (static)}"""
    reader = RrdReader(str(path))
    temporal, static = defaultdict(list), defaultdict(list)
    for ch in reader.stream().collect().stream().to_chunks():
        (static if ch.is_static else temporal)[ch.entity_path].append(ch)
    return reader, temporal, static


def _rows(chunks) -> int:
    return sum(ch.num_rows for ch in chunks)


def _column(chunks, name: str) -> list:
    return [v for ch in chunks for v in ch.to_record_batch().column(name).to_pylist()]


def _texts(chunks, name: str) -> list[str]:
    """Text components, one string per row (Rerun stores each row as a list)."""
    return [t for row in _column(chunks, name) for t in row]


def _scalars(chunks) -> list[float]:
    """Scalar values sorted by the `step` timeline."""
    pairs = zip(_column(chunks, "step"), _column(chunks, "Scalars:scalars"))
    return [v[0] for _, v in sorted(pairs)]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("run")
    model = TinyModule()
    trainer = _trainer(tmp)
    trainer.fit(model, _loader(), _loader())
    return tmp, model, trainer


def test_one_recording_with_blueprint(trained):
    tmp, _, _ = trained
    assert sorted(p.name for p in tmp.glob("*.rrd")) == ["run.rrd"]
    reader, _, _ = _read(tmp / "run.rrd")
    assert len(reader.recordings()) == 1
    assert reader.recordings()[0].application_id == "gaia_app"
    assert len(reader.blueprints()) >= 1


def test_train_loss_matches_logged_values(trained):
    tmp, model, _ = trained
    _, temporal, _ = _read(tmp / "run.rrd")
    chunks = temporal["/metrics/train/loss"]
    assert _rows(chunks) == 6
    assert _scalars(chunks) == pytest.approx(model.logged, rel=1e-6)
    assert sorted(_column(chunks, "step")) == list(range(6))
    # the video's `frame` timeline must not leak onto metrics logged after it
    assert all("frame" not in ch.timeline_names for ch in chunks)
    assert _rows(temporal["/metrics/val/loss"]) == 2


def test_hparams_document(trained):
    tmp, _, _ = trained
    _, _, static = _read(tmp / "run.rrd")
    text = _texts(static["/hparams"], "TextDocument:text")[-1]
    assert "lr: 0.05" in text and "width: 4" in text


def test_media_entities(trained):
    tmp, _, _ = trained
    _, temporal, _ = _read(tmp / "run.rrd")
    epochs = 2  # sanity-check validation is skipped
    assert _rows(temporal["/val/reconstruction"]) == epochs
    assert _rows(temporal["/val/tokens"]) == epochs
    assert _rows(temporal["/val/caption"]) == epochs * B
    video = temporal["/val/rollout"]
    assert _rows(video) == epochs * T
    assert sorted(set(_column(video, "frame"))) == list(range(T))
    assert sorted(set(_column(video, "step"))) == [3, 6]  # global_step after each epoch


def test_every_n_val_epochs(tmp_path):
    trainer = _trainer(tmp_path)
    trainer.callbacks[0].every_n_val_epochs = 2
    trainer.fit(TinyModule(), _loader(), _loader())
    _, temporal, _ = _read(tmp_path / "run.rrd")
    assert _rows(temporal["/val/reconstruction"]) == 1


def test_rerun_logger_of(trained):
    _, _, trainer = trained
    assert isinstance(rerun_logger_of(trainer), RerunLogger)
    assert rerun_logger_of(pl.Trainer(logger=False, accelerator="cpu")) is None


def test_flatten_params_dict_dictconfig_namespace():
    nested = {"model": {"net": {"depth": 2}, "lr": 1e-3}, "name": "x"}
    expected = {"model.lr": 1e-3, "model.net.depth": 2, "name": "x"}
    assert flatten_params(nested) == expected
    assert flatten_params(OmegaConf.create(nested)) == expected
    assert flatten_params(argparse.Namespace(**nested)) == expected
    assert flatten_params(OmegaConf.create({"a": 1, "b": "${a}"})) == {"a": 1, "b": 1}
    assert flatten_params({"f": torch.nn.Linear})["f"].startswith("<class")
    assert flatten_params(None) == {}


def test_the_logger_pickles_without_its_stream(tmp_path):
    """ddp_spawn ships the logger to its child processes: it pickles without the recording stream, and the copy
    keeps its settings (the two-process run itself is in the slow tier)."""
    import pickle

    logger = RerunLogger(str(tmp_path), version="v1")
    logger.log_metrics({"train/loss": 1.0}, step=0)  # opens the stream
    assert logger._rec is not None
    copy = pickle.loads(pickle.dumps(logger))
    assert copy._rec is None and copy.save_dir == logger.save_dir and copy.version == logger.version


def test_config_text_and_continuation(tmp_path):
    """log_config / log_text land in the file; reuse after finalize continues in run.1.rrd."""
    logger = RerunLogger(str(tmp_path), version="v1")
    logger.log_config(OmegaConf.create({"trainer": {"max_steps": 5}}))
    logger.log_text("/log", ["hello", "world"], step=3)
    logger.finalize("success")
    logger.log_metrics({"test/acc": 0.5}, step=7)
    logger.finalize("success")

    reader, temporal, static = _read(tmp_path / "run.rrd")
    assert "max_steps: 5" in _texts(static["/config"], "TextDocument:text")[0]
    assert _texts(temporal["/log"], "TextLog:text") == ["hello", "world"]
    reader2, temporal2, _ = _read(tmp_path / "run.1.rrd")
    assert reader2.recordings()[0].recording_id == reader.recordings()[0].recording_id == "gaia-v1"
    assert _scalars(temporal2["/metrics/test/acc"]) == [0.5]


def test_save_is_throttled_so_rows_share_chunks(tmp_path):
    """Lightning calls save() after every log_metrics; flushing each time bloats the .rrd ~40x."""
    logger = RerunLogger(str(tmp_path), flush_interval_s=60.0)
    for step in range(20):
        logger.log_metrics({"train/loss": float(step)}, step=step)
        logger.save()
    logger.finalize("success")
    _, temporal, _ = _read(tmp_path / "run.rrd")
    chunks = temporal["/metrics/train/loss"]
    assert _rows(chunks) == 20 and len(chunks) <= 2


def test_spawn_without_viewer_warns_and_records(tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(viewer, "viewer_executable", lambda: str(tmp_path / "no-such-rerun"))
    logger = RerunLogger(str(tmp_path), spawn=True, viewer_port=39871)
    with caplog.at_level(logging.WARNING, logger=rl.__name__):
        logger.log_metrics({"train/loss": 1.0}, step=0)
    logger.finalize("success")
    assert "writing" in caplog.text
    _, temporal, _ = _read(tmp_path / "run.rrd")
    assert _rows(temporal["/metrics/train/loss"]) == 1


def test_a_resumed_run_keeps_the_earlier_recording_and_continues_its_id(tmp_path, caplog):
    """A new process in the same run dir (ckpt_path=last) must not overwrite run.rrd: it writes run.1.rrd with the
    same recording id, so the viewer shows both launches as one recording."""
    first = RerunLogger(str(tmp_path))
    for step in range(3):
        first.log_metrics({"train/loss": float(step)}, step=step)
    first.finalize("success")
    size = (tmp_path / "run.rrd").stat().st_size
    resumed = RerunLogger(str(tmp_path))  # what the relaunched process builds from the same config
    with caplog.at_level(logging.INFO, logger=rl.__name__):
        for step in range(3, 5):
            resumed.log_metrics({"train/loss": float(step)}, step=step)
    resumed.finalize("success")
    assert (tmp_path / "run.rrd").stat().st_size == size
    assert "the earlier steps stay in" in caplog.text and "run*.rrd" in caplog.text
    readers = [_read(tmp_path / name) for name in ("run.rrd", "run.1.rrd")]
    assert [_rows(temporal["/metrics/train/loss"]) for _, temporal, _ in readers] == [3, 2]
    ids = {r.recording_id for reader, _, _ in readers for r in reader.recordings()}
    assert len(ids) == 1


def test_a_spawned_viewer_listens_on_loopback_unless_told_otherwise(tmp_path, monkeypatch):
    launched = []

    class FakeViewer:
        def __init__(self, args, **kwargs):
            launched.append(args)

        def poll(self):
            return None

    monkeypatch.setattr(viewer.subprocess, "Popen", FakeViewer)
    monkeypatch.setattr(viewer, "port_open", lambda host, port, timeout=0.5: bool(launched))
    monkeypatch.setattr(rl, "port_open", lambda host, port, timeout=0.5: False)
    monkeypatch.setattr(viewer, "viewer_executable", lambda: "rerun")
    for kwargs, address in (({}, "127.0.0.1"), ({"bind": "0.0.0.0"}, "0.0.0.0")):
        logger = RerunLogger(str(tmp_path / address), spawn=True, viewer_port=39872, **kwargs)
        assert logger._start_viewer()
        args = launched[-1]
        assert args[args.index("--bind") + 1] == address and args[args.index("--port") + 1] == "39872"
    cfg = OmegaConf.load(Path(__file__).resolve().parents[2] / "conf" / "logger" / "rerun.yaml")
    assert cfg.rerun.bind == "127.0.0.1"


@pytest.mark.slow
def test_ddp_two_processes_write_one_recording(tmp_path):
    """2 CPU processes (gloo): only rank 0 writes; each rank runs 2 of the 3 batches per epoch."""
    trainer = _trainer(tmp_path, strategy="ddp_spawn", devices=2)
    trainer.fit(TinyModule(), _loader(), _loader())
    assert [p.name for p in tmp_path.rglob("*.rrd")] == ["run.rrd"]
    reader, temporal, _ = _read(tmp_path / "run.rrd")
    assert len(reader.recordings()) == 1
    assert _rows(temporal["/metrics/train/loss"]) == 4
    assert _rows(temporal["/val/rollout"]) == 2 * T
