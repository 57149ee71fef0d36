"""Lightning logger that writes one Rerun recording (.rrd) per run, from rank 0 only (DESIGN §8).

Entities: /metrics/<key> scalars on the `step` timeline, /hparams and /config static Markdown,
text logs at caller-chosen paths. Media come from `gaia_app.viz.callbacks.RerunMediaCallback`.
"""

from __future__ import annotations

import argparse
import logging
import os
import time
import uuid
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import torch
import yaml
from lightning.pytorch.loggers import Logger
from lightning.pytorch.loggers.logger import rank_zero_experiment
from lightning.pytorch.utilities import rank_zero_only
from omegaconf import DictConfig, ListConfig, OmegaConf

from gaia_app.viz.blueprints import training_blueprint
from gaia_app.viz.viewer import LOOPBACK, ViewerUnavailable, connect_host, port_open, spawn_viewer

log = logging.getLogger(__name__)

_FLUSH_TIMEOUT_S = 10.0


def _to_plain(params: Any) -> Any:
    """Turn DictConfig / Namespace / Mapping (recursively) into plain dicts and lists."""
    if isinstance(params, (DictConfig, ListConfig)):
        try:
            return OmegaConf.to_container(params, resolve=True)
        except Exception:  # noqa: BLE001  e.g. ${hydra:...} outside @hydra.main: keep it unresolved
            return OmegaConf.to_container(params, resolve=False)
    if isinstance(params, argparse.Namespace):
        params = vars(params)
    if isinstance(params, Mapping):
        return {str(k): _to_plain(v) for k, v in params.items()}
    if isinstance(params, (list, tuple)):
        return [_to_plain(v) for v in params]
    return params


def _yaml_scalar(v: Any) -> Any:
    """Keep YAML-native leaves; render anything else (tensors, partials, classes) with repr."""
    if v is None or isinstance(v, (bool, int, float, str)):
        return v
    if isinstance(v, np.generic) or (isinstance(v, torch.Tensor) and v.numel() == 1):
        return v.item()
    if isinstance(v, list) and all(isinstance(x, (bool, int, float, str)) for x in v):
        return v
    return repr(v)


def flatten_params(params: Any, delimiter: str = ".") -> dict[str, Any]:
    """Flatten nested hyperparameters to {"model.net.depth": 12, ...}, sorted by key.

    params: dict, DictConfig, argparse.Namespace or None.
    """
    out: dict[str, Any] = {}

    def walk(node: Any, prefix: str) -> None:
        if isinstance(node, dict) and (node or not prefix):  # an empty nested dict stays a leaf
            for k, v in node.items():
                walk(v, f"{prefix}{delimiter}{k}" if prefix else str(k))
        else:
            out[prefix] = _yaml_scalar(node)

    walk(_to_plain(params) or {}, "")
    return dict(sorted(out.items()))


def _markdown_yaml(title: str, data: Any) -> rr.TextDocument:
    """A Markdown document with a title and a YAML code block."""
    body = yaml.safe_dump(data, sort_keys=False, default_flow_style=False, allow_unicode=True)
    return rr.TextDocument(f"# {title}\n\n```yaml\n{body}```\n", media_type=rr.MediaType.MARKDOWN)


def _entity(key: str, root: str) -> list[str]:
    """`train/loss` -> ["metrics", "train", "loss"]; a list lets Rerun escape odd characters."""
    return [root, *[p for p in key.split("/") if p]]


class RerunLogger(Logger):
    """Write one Rerun recording per run to `<save_dir>/<recording_file>`, rank 0 only.

    save_dir: the run directory (Hydra's run dir in gaia_app).
    spawn: also stream live to a Rerun viewer on `viewer_port` (reusing one already listening
        there). Where no viewer can be started (no binary, no display) a warning is logged and
        only the file is written: visualisation never stops training.
    bind: the address a spawned viewer listens on: loopback by default (the `rerun` binary's own default is every
        interface); "0.0.0.0" shares the live view with the network.
    flush_interval_s: how long rows are batched into one chunk before they reach the file/viewer.
        Every flush closes the open chunks, and a chunk costs ~1 kB, so flushing on each logging
        step (Lightning calls `save()` after every `log_metrics`) made the .rrd ~40x larger.
    After `finalize` (end of fit/validate/test) a later use of the logger continues the same
    recording id in `<stem>.<n>.rrd`; the viewer merges files that share a recording id. A resumed run (a new
    process in the same run dir) does the same: the earlier launches' files are kept, the new one writes the next
    free `<stem>.<n>.rrd`, and without a `version` the recording id derives from the run dir, so
    `rerun <run dir>/run*.rrd` shows the whole history as one recording.
    """

    def __init__(
        self,
        save_dir: str,
        name: str = "gaia",
        version: str | None = None,
        recording_file: str = "run.rrd",
        spawn: bool = False,
        application_id: str = "gaia_app",
        viewer_port: int = 9876,
        flush_interval_s: float = 2.0,
        bind: str = LOOPBACK,
    ) -> None:
        super().__init__()
        self._save_dir = os.fspath(save_dir)
        self._name = name
        self._version = version
        self._recording_file = recording_file
        self._spawn = spawn
        self._application_id = application_id
        self._viewer_port = viewer_port
        self._bind = bind
        self._flush_interval_s = flush_interval_s
        self._last_flush = 0.0
        self._recording_id: str | None = None  # chosen on rank 0 at first use
        self._rec: rr.RecordingStream | None = None
        self._segment = 0  # files written so far (>1 when fit and test share the logger)
        self._hparams: dict[str, Any] = {}
        self._media_paths: list[str] = []
        self._flush_failed = False

    def __getstate__(self) -> dict[str, Any]:
        """Pickle without the stream (ddp_spawn ships the logger to child processes)."""
        return {**self.__dict__, "_rec": None}

    @property
    def name(self) -> str:
        return self._name

    @property
    def version(self) -> str | int:
        return self._version if self._version is not None else 0

    @property
    def save_dir(self) -> str:
        return self._save_dir

    @property
    def recording_path(self) -> Path:
        """Path of the .rrd being written (the first one is `<save_dir>/<recording_file>`)."""
        path = Path(self._save_dir) / self._recording_file
        return path if self._segment <= 1 else path.with_suffix(f".{self._segment - 1}{path.suffix}")

    @property
    @rank_zero_experiment
    def experiment(self) -> rr.RecordingStream:
        """The run's RecordingStream (a DummyExperiment on ranks > 0); opened on first use."""
        if self._rec is None:
            self._rec = self._open()
        return self._rec

    def _open(self) -> rr.RecordingStream:
        """Create the stream, attach the file sink (and the live viewer), send the blueprint."""
        self._segment += 1
        while self.recording_path.exists():  # an earlier launch's file (a resumed run): keep it, write the next
            self._segment += 1
        if self._recording_id is None:
            self._recording_id = f"{self._name}-{self._version if self._version is not None else self._run_dir_id()}"
        rec = rr.RecordingStream(
            self._application_id,
            recording_id=self._recording_id,
            batcher_config=rr.ChunkBatcherConfig(flush_tick=self._flush_interval_s),
        )
        path = self.recording_path
        path.parent.mkdir(parents=True, exist_ok=True)
        sinks: list[Any] = [rr.FileSink(str(path))]
        if self._spawn and self._start_viewer():
            sinks.append(rr.GrpcSink(f"rerun+http://{connect_host(self._bind)}:{self._viewer_port}/proxy"))
        rec.set_sinks(*sinks, default_blueprint=self.blueprint())
        if self._segment > 1:
            first = Path(self._save_dir) / self._recording_file
            log.info("Rerun: continuing recording %s in %s; the earlier steps stay in %s (open them together: "
                     "rerun %s)", self._recording_id, path, first, first.with_name(f"{first.stem}*{first.suffix}"))
        return rec

    def _run_dir_id(self) -> str:
        """A recording id suffix fixed by the run dir: every launch of one run (resumes) continues one recording."""
        return uuid.uuid5(uuid.NAMESPACE_URL, str(Path(self._save_dir).resolve())).hex[:8]

    def _start_viewer(self) -> bool:
        """Spawn (or reuse) a viewer on bind:port; False with a warning when none is reachable."""
        if port_open(connect_host(self._bind), self._viewer_port):
            return True
        try:
            spawn_viewer(self._viewer_port, self._bind)
        except (ViewerUnavailable, OSError) as err:  # missing binary, no display: keep the file only
            log.warning("Rerun: could not start a viewer (%s); writing %s only", err, self.recording_path)
            return False
        return True

    def blueprint(self) -> rrb.Blueprint:
        """The default training layout, with the media paths registered so far."""
        return training_blueprint(media_paths=self._media_paths)

    @rank_zero_only
    def add_media_paths(self, paths: Iterable[str]) -> None:
        """Register media entities and re-send the layout so each gets its own view."""
        new = [p for p in paths if p not in self._media_paths]
        if new:
            self._media_paths.extend(new)
            self.experiment.send_blueprint(self.blueprint(), make_active=True, make_default=True)

    @rank_zero_only
    def log_hyperparams(self, params: Any, *args: Any, **kwargs: Any) -> None:
        """Log flattened hyperparameters as a static Markdown/YAML document at /hparams.

        params: dict, DictConfig or argparse.Namespace; repeated calls accumulate.
        """
        self._hparams.update(flatten_params(params))
        doc = _markdown_yaml("Hyperparameters", dict(sorted(self._hparams.items())))
        self.experiment.log("/hparams", doc, static=True)

    @rank_zero_only
    def log_config(self, config: Any) -> None:
        """Log the (resolved) run config as a static Markdown/YAML document at /config.

        config: the Hydra DictConfig of the run (or any mapping). Called by the train task.
        """
        self.experiment.log("/config", _markdown_yaml("Config", _to_plain(config)), static=True)

    @rank_zero_only
    def log_metrics(self, metrics: Mapping[str, float], step: int | None = None) -> None:
        """Log each metric as rr.Scalars at /metrics/<key> on the `step` timeline."""
        rec = self.experiment
        rec.set_time("step", sequence=int(step or 0))
        for key, value in metrics.items():
            value = value.item() if isinstance(value, torch.Tensor) else value
            rec.log(_entity(key, "metrics"), rr.Scalars(float(value)))

    @rank_zero_only
    def log_text(self, path: str, text: str | Sequence[str], step: int | None = None) -> None:
        """Log text as rr.TextLog rows at `path` (one row per string), at `step` when given."""
        rec = self.experiment
        if step is not None:
            rec.set_time("step", sequence=int(step))
        for line in [text] if isinstance(text, str) else text:
            rec.log(path, rr.TextLog(line))

    @rank_zero_only
    def save(self) -> None:
        """Flush buffered data, at most once per flush_interval_s (see the class docstring)."""
        # after a failed flush (dead live viewer) each retry would block ~1 s; the file sink
        # keeps writing in the background and finalize flushes once more
        due = time.monotonic() - self._last_flush >= self._flush_interval_s
        if self._rec is not None and due and not self._flush_failed:
            self._flush(self._rec)

    @rank_zero_only
    def finalize(self, status: str) -> None:
        """Flush and close the sinks so the .rrd footer is written."""
        if self._rec is None:
            return
        self._flush(self._rec)
        self._rec.disconnect()
        self._rec = None

    def _flush(self, rec: rr.RecordingStream) -> None:
        """Flush; a vanished live viewer makes flush raise, which must not stop training."""
        self._last_flush = time.monotonic()
        try:
            rec.flush(timeout_sec=_FLUSH_TIMEOUT_S)
        except RuntimeError as err:
            if not self._flush_failed:
                log.warning("Rerun: flush failed (%s); the file sink keeps recording", err)
            self._flush_failed = True


def rerun_logger_of(trainer: pl.Trainer) -> RerunLogger | None:
    """The trainer's RerunLogger, or None when the run does not log to Rerun."""
    return next((lg for lg in trainer.loggers if isinstance(lg, RerunLogger)), None)
