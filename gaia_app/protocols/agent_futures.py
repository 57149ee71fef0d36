"""Futures with moving agents: does the lead vehicle stay, react to the ego and vary across futures? (issue 49 item 3)

GAIA-1 §7.2 (multiple plausible futures in which other agents behave differently) and §7.3 (agents reacting to the
ego), measured on held-out contexts of the synthetic world that have a vehicle ahead in the ego lane within 30 m at
the last context frame. Each context is continued under the four commands of the controllability table (brake,
accelerate, left, right), the futures of one context sharing their sampling noise, and the synthetic world
re-simulates the same scene under the same commands (the real continuations, whose labels give the true gaps).
The agent segmentation probe reads every frame; `gaia_app/eval/lead_gap.py` turns its mask into the gap to the lead
vehicle.

- persistence: of the future frames whose real continuation has a lead vehicle within 30 m, the share in which
  one is read (rows: the real continuation itself, its tokenizer round trip (the ceiling of any world model over
  these tokens), the model's futures); and of the frames in which the reader finds it in the real continuation
  (a vehicle the reader cannot see in the real frame, e.g. unlit at night, cannot be asked of a future);
- interaction: the share of contexts whose gap at the horizon is smaller under "accelerate" than under "brake"
  (rows: the world's labels, the read real continuation, its round trip, the model);
- multiple futures: per context, the spread of the horizon gap over `futures` futures sampled under the real
  continuation's own actions with independent noise, against the spread over as many renderings of the real
  continuation's tokens (zero when frames are decoded by the tokenizer, which is deterministic).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from gaia_app.data.clip import Clip
from gaia_app.data.transforms import resample_clip, to_float
from gaia_app.eval.agent_fidelity import VEHICLES
from gaia_app.eval.agent_iou import predicted_agents
from gaia_app.eval.controllability import ProbeClips
from gaia_app.eval.intervals import share_interval
from gaia_app.eval.lead_gap import (
    LEAD_RANGE,
    READ_RANGE,
    GroundPlane,
    closer_under,
    commanded_pose,
    gap_error,
    ground_plane,
    labelled_gaps,
    lead_gaps,
    persistence,
    spread,
)
from gaia_app.models.probes import AgentSegmentationProbe
from gaia_app.pipelines.gaia1 import Gaia1Pipeline
from gaia_app.protocols.controllability import (
    commanded_actions,
    context_groups,
    driven_clip,
    rollout_frames,
    tokenized,
    world,
)

COMMANDS = (("brake", "straight"), ("accelerate", "straight"), ("keep", "left"), ("keep", "right"))


@dataclass
class Continuations:
    """Real clips at the world model's rate: frames (N, T, 3, H, W) in [-1, 1], actions (N, T, 2), the world's lead
    gaps (N, T) (NaN: no lead vehicle, at any distance the label reports) and the front camera."""

    frames: torch.Tensor
    actions: torch.Tensor
    gaps: np.ndarray
    ground: GroundPlane


def at_rate(clip: Clip, rate: float, frames: int) -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
    """(frames (T, 3, H, W), actions (T, 2), labelled lead gaps (T,), at any distance) of the front camera,
    resampled to `rate`."""
    clip = resample_clip(clip, rate)
    if clip.frames.shape[1] < frames or clip.actions is None or clip.frame_meta is None:
        raise ValueError(f"agent futures: clip '{clip.clip_id}' has {clip.frames.shape[1]} frames at {rate:g} Hz "
                         f"({frames} needed) and needs actions and frame_meta")
    video = to_float(torch.from_numpy(np.ascontiguousarray(clip.frames[0, :frames])))
    gaps = labelled_gaps(clip.frame_meta[:frames], VEHICLES, np.inf)
    return video, torch.from_numpy(clip.actions[:frames]).float(), gaps


def stack(parts: list[tuple[torch.Tensor, torch.Tensor, np.ndarray]], ground: GroundPlane) -> Continuations:
    frames, actions, gaps = zip(*parts)
    return Continuations(torch.stack(frames), torch.stack(actions), np.stack(gaps), ground)


def lead_contexts(seed: int, count: int, height: int, width: int, t0: int, total: int, rate: float,
                  scan: int) -> tuple[list[int], Continuations]:
    """The first `count` clips of the world `seed` (of at most `scan`) with a lead vehicle within 30 m at context
    frame t0 − 1, and their own continuations (`total` frames at `rate`)."""
    clips = world(seed, scan, height, width, total, rate, every_frame=False)
    chosen, parts = [], []
    for index in tqdm(range(scan), desc="contexts with a lead vehicle", leave=False):
        part = at_rate(clips[index], rate, total)
        if part[2][t0 - 1] <= LEAD_RANGE:
            chosen.append(index)
            parts.append(part)
            if len(chosen) == count:
                return chosen, stack(parts, ground_plane(clips[index].cameras[0]))
    raise ValueError(f"agent futures: {len(chosen)} of the first {scan} clips of world {seed} have a lead vehicle "
                     f"within {LEAD_RANGE:g} m at context frame {t0 - 1}, {count} needed (raise the scan)")


def resimulated(seed: int, indices: list[int], height: int, width: int, commanded: torch.Tensor, t0: int,
                rate: float, ground: GroundPlane) -> Continuations:
    """The scenes of `indices` driven by each row of `commanded` (C·N, T, 2), command-major."""
    n, total = len(indices), commanded.shape[1]
    parts = [at_rate(driven_clip(seed, indices[i % n], height, width, commanded[i].numpy(), t0, rate,
                                 every_frame=False), rate, total) for i in range(len(commanded))]
    return stack(parts, ground)


def read_gaps(probe: AgentSegmentationProbe, frames: torch.Tensor, actions: torch.Tensor, lane_curvature: torch.Tensor,
              ground: GroundPlane, rate: float) -> np.ndarray:
    """(N, t) lead gaps the probe reads on frames (N, t, 3, H, W) of futures under commanded actions (N, t, 2), the
    lane keeping the road's curvature (N,) (the context's last) while the commands may turn the ego off it."""
    with torch.no_grad():
        masks = predicted_agents(probe, frames)
    return lead_gaps(masks, commanded_pose(actions, lane_curvature, rate), ground)


def within(gaps: np.ndarray, limit: float) -> np.ndarray:
    """The gaps at most `limit` m, NaN elsewhere."""
    return np.where(gaps <= limit, gaps, np.nan)


def score_reading(read: np.ndarray, labelled: np.ndarray) -> dict[str, Any]:
    """How well the reader agrees with the world's labels (gaps at any distance) on real frames: found where a lead
    vehicle is labelled within 30 m, read where none is labelled within the reading range, and the gap error."""
    present, anywhere = np.isfinite(within(labelled, LEAD_RANGE)), np.isfinite(within(labelled, READ_RANGE))
    error = gap_error(read, within(labelled, LEAD_RANGE))
    return {"found_where_labelled": float((np.isfinite(read) & present).sum() / max(present.sum(), 1)),
            "read_where_none": float((np.isfinite(read) & ~anywhere).sum() / max((~anywhere).sum(), 1)),
            "gap_error_m": None if error is None else error.as_dict()}


def interaction_row(gaps: np.ndarray, commands: list[tuple[str, str]]) -> dict[str, Any]:
    """Share of contexts whose horizon gap is smaller under accelerate than under brake; gaps (C, N, t)."""
    names = ["/".join(c) for c in commands]
    accelerate, brake = names.index("accelerate/straight"), names.index("brake/straight")
    closer = closer_under(gaps[accelerate, :, -1], gaps[brake, :, -1])
    return {"share": share_interval(int(closer.sum()), len(closer)).as_dict(),
            "per_context": closer.astype(int).tolist()}


def futures_spread(pipeline: Gaia1Pipeline, probe: AgentSegmentationProbe, own: Continuations, t0: int,
                   futures: int, contexts: int, generator: torch.Generator) -> tuple[dict[str, Any], torch.Tensor]:
    """Spread of the horizon gap over `futures` independent futures of each of the first `contexts` contexts under
    their own actions, against `futures` renderings of the real continuation's tokens (a video decoder's renderings
    differ; the tokenizer's are identical); and the futures of the first context (futures, t, 3, H, W) for the
    gallery. A context's futures are wider when their spread exceeds the renderings' (missing counts as none)."""
    frames = own.frames.shape[1] - t0
    rows: dict[str, list] = {"model_spread_m": [], "model_found": [], "round_trip_spread_m": [],
                             "round_trip_found": []}
    first = None
    for i in range(contexts):
        actions = own.actions[i:i + 1].repeat(futures, 1, 1)
        video = rollout_frames(pipeline, own.frames[i:i + 1, :t0].repeat(futures, 1, 1, 1, 1), frames, futures,
                               None, actions, generator)[:, t0:]  # the rollouts start with the context
        first = video if first is None else first
        tokens = pipeline.encode(own.frames[i]).unsqueeze(0).repeat(futures, 1, 1, 1)
        rendered = pipeline.render(tokens, generator)[0][:, t0:]
        for name, frames_read in (("model", video), ("round_trip", rendered)):
            horizon = read_gaps(probe, frames_read, actions[:, t0:], actions[:, t0 - 1, 1], own.ground,
                                pipeline.rate)[:, -1]
            rows[f"{name}_spread_m"].append(spread(horizon))
            rows[f"{name}_found"].append(int(np.isfinite(horizon).sum()))
    wider = [m is not None and m > (r or 0.0) for m, r in zip(rows["model_spread_m"], rows["round_trip_spread_m"])]
    return {"futures": futures, **rows, "wider_than_round_trips": share_interval(sum(wider), len(wider)).as_dict()}, \
        first


def agent_futures(pipeline: Gaia1Pipeline, probe: AgentSegmentationProbe, seed: int, contexts: int, t0: int,
                  frames: int, generator: torch.Generator, futures: int = 8, spread_contexts: int = 4,
                  scan: int = 400) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """The persistence, interaction and multiple-futures tables of `contexts` held-out contexts of world `seed`
    (t0 context frames, `frames` future frames at the pipeline's rate), and the videos for the gallery."""
    (height, width), rate, total = pipeline.image_size, pipeline.rate, t0 + frames
    indices, own = lead_contexts(seed, contexts, height, width, t0, total, rate, scan)
    commands = [tuple(c) for c in COMMANDS]
    probe_clips = ProbeClips(own.frames, own.actions, {})
    commanded = commanded_actions(probe_clips, t0, frames, rate, commands)
    real = resimulated(seed, indices, height, width, commanded, t0, rate, own.ground)
    videos = {"real": real.frames[:, t0:], "tokenized": tokenized(pipeline, real.frames)[:, t0:],
              "model": rollout_frames(pipeline, own.frames[:, :t0].repeat(len(commands), 1, 1, 1, 1), frames,
                                      len(commanded), None, commanded, generator,
                                      context_groups(len(commands), contexts))[:, t0:]}
    future_actions, road = commanded[:, t0:], commanded[:, t0 - 1, 1]  # the road's curvature: the context's last
    read = {name: read_gaps(probe, video, future_actions, road, own.ground, rate) for name, video in videos.items()}
    labelled = within(real.gaps[:, t0:], LEAD_RANGE)
    per_command = (len(commands), contexts, frames)
    interaction = {"labels": interaction_row(labelled.reshape(per_command), commands)}
    interaction |= {name: interaction_row(gaps.reshape(per_command), commands) for name, gaps in read.items()}
    by_context = lambda x: x.reshape(per_command).transpose(1, 0, 2).reshape(contexts, -1)  # noqa: E731
    labelled_present, visible = by_context(np.isfinite(labelled)), by_context(np.isfinite(read["real"]))
    persist = {name: persistence(by_context(np.isfinite(gaps)), labelled_present).as_dict()
               for name, gaps in read.items()}
    persist_visible = {name: persistence(by_context(np.isfinite(read[name])), visible).as_dict()
                       for name in ("tokenized", "model")}
    spread_table, gallery = futures_spread(pipeline, probe, own, t0, futures, spread_contexts, generator)
    results = {"world_seed": seed, "clip_indices": indices, "contexts": contexts, "context_frames": t0,
               "future_frames": frames, "rate": rate, "commands": [list(c) for c in commands],
               "reader_on_real_frames": score_reading(read["real"], real.gaps[:, t0:]), "persistence": persist,
               "persistence_where_read_in_real": persist_visible,
               "interaction": interaction, "multiple_futures": spread_table}
    return results, {"futures": gallery, "real": own.frames[0:1, t0:]}


def markdown(results: dict[str, Any]) -> str:
    """The three tables of `agent_futures` as markdown."""
    def cell(e: dict[str, float]) -> str:
        return f"{e['mean']:.2f} [{e['low']:.2f}, {e['high']:.2f}]"

    reader = results["reader_on_real_frames"]
    error = reader["gap_error_m"]
    lines = [f"{results['contexts']} contexts of world {results['world_seed']} with a lead vehicle within 30 m, "
             f"{results['context_frames']} context frames, {results['future_frames']} future frames at "
             f"{results['rate']:g} Hz; the reader on real frames finds {reader['found_where_labelled']:.2f} of the "
             f"labelled lead vehicles, reads one in {reader['read_where_none']:.2f} of the frames with none within "
             f"{READ_RANGE:g} m, gap error "
             f"{'—' if error is None else cell(error)} m", "",
             "| row | persistence: of the labelled frames (target ≥ 0.8) | of the frames where it is read in the real "
             "continuation | closer under accelerate than brake (target ≥ 0.8) |",
             "|---|---:|---:|---:|", f"| world labels | — | — | {cell(results['interaction']['labels']['share'])} |"]
    names = {"real": "real continuation, read", "tokenized": "tokenizer round trip (ceiling)", "model": "model"}
    visible = results["persistence_where_read_in_real"]
    for key, name in names.items():
        lines.append(f"| {name} | {cell(results['persistence'][key])} | "
                     f"{cell(visible[key]) if key in visible else '1 (by definition)'} | "
                     f"{cell(results['interaction'][key]['share'])} |")
    spread_table = results["multiple_futures"]
    spreads = ", ".join("—" if m is None else f"{m:.1f}" for m in spread_table["model_spread_m"])
    found = ", ".join(str(k) for k in spread_table["model_found"])
    lines += ["", f"Multiple futures ({spread_table['futures']} per context, {len(spread_table['model_found'])} "
                  f"contexts): the lead vehicle is read at the horizon in {found} of them; the spread of its gap over "
                  f"those is {spreads} m, against "
                  f"{', '.join('—' if r is None else f'{r:.1f}' for r in spread_table['round_trip_spread_m'])} m for "
                  f"renderings of the real continuation; wider in {cell(spread_table['wider_than_round_trips'])} of "
                  "the contexts"]
    return "\n".join(lines) + "\n"
