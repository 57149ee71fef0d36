"""`generate.py mode=evaluate`: fidelity and motion of GAIA-1 rollouts against the real continuations.

Fréchet distances compare sets, so this is a mode over `evaluate.contexts` clips of the synthetic world
(`context.seed`) rather than a flag on a single rollout. Every context is continued for `seconds` (mode=video,
no condition) and scored at the world model's rate against the clip's real continuation:

    model       the world model's futures, rendered by the pipeline (video decoder, else frame by frame)
    tokens      the real continuation tokenized and rendered the same way: the best a perfect world model
                could score through this tokenizer and decoder (the ceiling)
    held frame  the last context frame repeated: a future that never moves (a floor for motion)

Metrics (`evaluate.metrics`, docs/evaluation.md): psnr / ssim / lpips (needs `evaluate.lpips_checkpoint`) per
generated frame against the real one, fvmd
between the sets of real and generated clips (last context frame + future), fid / fdd over future frames
(need `evaluate.fid_checkpoint` / `evaluate.fdd_checkpoint`), agent_iou of a segmentation probe's agent masks on
generated frames with the real frames' agent masks (the probe trains in the run on `evaluate.probe_clips` clips of
the world `evaluate.probe_seed`; its IoU on the real frames themselves is reported too). Writes evaluation.json and
the table evaluation.md into the run dir.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig

from gaia_app.eval.agent_iou import agent_clips, agent_iou, train_agent_probe
from gaia_app.eval.controllability import probe_clips
from gaia_app.models.probes import AgentSegmentationProbe
from gaia_app.pipelines.gaia1_inputs import future_frames
from gaia_app.protocols.controllability import rollout_frames, world_samples
from gaia_app.protocols.fidelity import ARROWS, check_metrics, feature_metrics, held_frame, score
from gaia_app.protocols.loading import load_pipeline
from gaia_app.utils.run_dir import atomic_write_text


def check_settings(cfg: DictConfig) -> None:
    """Named errors before any work: unknown metrics, fdd without a checkpoint, too few contexts."""
    check_metrics(cfg.evaluate)
    if cfg.evaluate.contexts < 2:
        raise ValueError(f"evaluate.contexts={cfg.evaluate.contexts}: Fréchet distances need at least 2 clips per set")


def agent_probe(cfg: DictConfig, samples: list, height: int, width: int, frames: int, rate: float
                ) -> tuple[tuple[AgentSegmentationProbe, torch.Tensor], dict[str, float]]:
    """Train the agent probe on the probe world; returns (probe, the contexts' masks) and the fit summary."""
    e = cfg.evaluate
    train = world_samples(e.probe_seed, e.probe_clips, height, width, frames, rate)
    probe, fit = train_agent_probe(*agent_clips(train, rate, frames), steps=e.probe_steps, seed=cfg.seed)
    return (probe, agent_clips(samples, rate, frames)[1]), fit


def markdown(results: dict[str, Any]) -> str:
    names = list(next(iter(results["rows"].values())))
    lines = ["| rollouts vs real continuations | " + " | ".join(f"{n} {ARROWS[n]}" for n in names) + " |",
             "|---" * (len(names) + 1) + "|"]
    lines += [f"| {row} | " + " | ".join(f"{values[n]:.3f}" for n in names) + " |"
              for row, values in results["rows"].items()]
    if "agent_probe" in results:
        lines += ["", "agent probe IoU on the real future frames themselves: "
                  f"{results['agent_probe']['iou_on_real_future']:.3f}"]
    return "\n".join(lines) + "\n"


def evaluate(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Run the protocol of the module docstring; returns the results (also written to the run dir)."""
    check_settings(cfg)
    pipeline = load_pipeline(cfg)
    rate, (height, width), n = pipeline.rate, pipeline.image_size, cfg.evaluate.contexts
    t0, frames = cfg.context.frames, future_frames(cfg.seconds, rate, at_least=2)
    samples = world_samples(cfg.context.seed, n, height, width, t0 + frames, rate)
    real = probe_clips([s.clip for s in samples], rate, t0 + frames).frames
    agents, extra = None, {}
    if "agent_iou" in cfg.evaluate.metrics:
        agents, fit = agent_probe(cfg, samples, height, width, t0 + frames, rate)
        extra = {"agent_probe": {**fit, "iou_on_real_future": agent_iou(agents[0], real[:, t0:], agents[1][:, t0:])}}
    generator = torch.Generator(device=pipeline.device).manual_seed(int(cfg.seed))
    model = rollout_frames(pipeline, real[:, :t0], frames, n, None, None, generator)
    tokens = torch.stack([pipeline.encode(clip) for clip in real])
    reconstructed = pipeline.render(tokens, generator)[0]
    held = held_frame(real, t0)
    metrics, networks = list(cfg.evaluate.metrics), feature_metrics(cfg.evaluate)
    rows = {name: score(metrics, real, candidate, t0, networks, agents) for name, candidate in (
        ("model (video rollouts)", model), ("tokens (real continuation, tokenized and rendered)", reconstructed),
        ("held frame (last context frame repeated)", held))}
    results = {"contexts": n, "context_frames": t0, "generated_frames": frames, "rate": rate, "rows": rows, **extra}
    atomic_write_text(run_dir / "evaluation.json", json.dumps(results, indent=2))
    table = markdown(results)
    atomic_write_text(run_dir / "evaluation.md", table)
    print(table)  # the one table the command is run for
    return results
