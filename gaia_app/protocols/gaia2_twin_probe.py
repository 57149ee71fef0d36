"""The GAIA-2 action table's twin probe: the speed contrast read from two futures of one scene at the same instant.

Legend: N scenes, C commands, D noise draws, f frames, t0 the first generated frame, s the probe stride, k cameras.

The table scores the horizon-mean speed difference of the accelerate and brake futures of one context
(controllability.contrast_errors). The inverse-dynamics probe reads it as the mean over the scored pairs
(i − s, i) of each future's own speed, and on re-simulated futures it reads about half of it, so its own check
(ceiling ≤ ½ floor) fails on most worlds (docs/latent_world_model_notes.md, "Why the speed probe reads about half…").
The same quantity telescopes into displacements: with Δs(i) how much further the accelerate future's ego has
travelled than the brake future's at frame i,

    Σ_{i = t0 + s}^{f − 1} (v̄_high(i) − v̄_low(i)) · s·dt = Σ_{i = f − s}^{f − 1} Δs(i) − Σ_{i = t0}^{t0 + s − 1} Δs(i),

so the horizon-mean contrast is that sum over (f − t0 − s) · s · dt. The twin probe (models/probes.py
TwinDisplacementProbe) reads Δs(i) from the two futures' frames i side by side: metres of displacement where the
pair probe reads a pixel of motion, and nothing else in the world differs between the two frames. With
`model.evaluate.speed_probe=twin` the table's speed contrast is read this way (the pair probe's reading stays in the
JSON as `speed_contrast_pair`); curvature is read by the pair probe either way.

Training (`twin_data`): each of `probe_clips` scenes of the world `probe_seed` (weather and time of day uniform)
follows its policy up to a random frame t0 ∈ [1, f − 2] and then two random constant accelerations (the range of
data/synthetic/commands.py) under one shared random curvature, so both twins drive the same path and differ in how
far along it they are; both are rendered, every camera the action probe reads. Targets: Δs(i) = Σ_{j < i}
(v_b(j) − v_a(j)) · dt, a_j moving the ego from frame j to j + 1 as in the synthetic world's driver.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig
from tqdm.auto import tqdm

from gaia_app.data.synthetic.commands import ACCELERATION_RANGE, command_profile, draw_command
from gaia_app.data.synthetic.rig import resolve_camera_names
from gaia_app.data.synthetic.scenario import Scenario
from gaia_app.data.transforms import to_float
from gaia_app.eval.controllability import augment_pairs, jitter, strided_actions
from gaia_app.eval.intervals import mean_interval
from gaia_app.models.probes import TwinDisplacementProbe
from gaia_app.protocols.controllability import UNIFORM_MIX, by_context
from gaia_app.protocols.gaia2_action_probe import load_saved_probe, save_action_probe
from gaia_app.protocols.gaia2_action_probe import probe_info as action_probe_info
from gaia_app.protocols.gaia2_actions import probe_mirror, probe_views, rig_world

SPEED_PROBES = ("pair", "twin")  # what reads the action table's speed contrast
WEIGHTS, INFO = "twin_probe.safetensors", "twin_probe.yaml"
MUST_MATCH = ("cameras", "probe_cameras", "image_size", "rate")
TWIN_STREAM = 77  # the twins' random commands: a stream of their own, apart from the probe world's scenes


@dataclass
class Twins:
    """frames (N, 2, f, k, 3, H, W) uint8 of two futures per scene (k = 1 for the front camera alone), displacement
    (N, f) m of the second future's ego ahead of the first's at each frame, start (N,) the first frame at which the
    twins can differ (t0 + 1)."""

    frames: torch.Tensor
    displacement: torch.Tensor
    start: torch.Tensor


def speed_probe(cfg: DictConfig) -> str:
    """`model.evaluate.speed_probe`, ValueError naming it unless one of SPEED_PROBES."""
    value = cfg.model.evaluate.get("speed_probe", "pair")
    if value not in SPEED_PROBES:
        raise ValueError(f"model.evaluate.speed_probe={value!r}: expected one of {SPEED_PROBES}")
    return value


def twin_actions(rng: np.random.Generator, own: np.ndarray, rate: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Two (f, 2) action sequences that share `own` (f, 2) up to a random frame t0 ∈ [1, f − 2], then each a random
    constant acceleration from the speed at t0 − 1 under one shared curvature; and t0."""
    frames = len(own)
    if frames < 3:
        raise ValueError(f"twin_actions: clips of at least 3 frames are needed, got {frames}")
    t0 = int(rng.integers(1, frames - 1))
    curvature = draw_command(rng)[1]
    twins = [np.concatenate([own[:t0], command_profile(float(own[t0 - 1, 0]), float(rng.uniform(*ACCELERATION_RANGE)),
                                                       curvature, frames - t0, 1.0 / rate)]) for _ in range(2)]
    return twins[0].astype(np.float64), twins[1].astype(np.float64), t0


def displacement(first: np.ndarray | torch.Tensor, second: np.ndarray | torch.Tensor, rate: float) -> torch.Tensor:
    """(…, f) m the second ego is ahead of the first at each frame, from their (…, f, 2) actions (speed m/s first):
    frame i has moved by Σ_{j < i} v_j · dt, so frame 0 reads 0 and the last action moves past the clip."""
    gap = torch.as_tensor(second)[..., 0].double() - torch.as_tensor(first)[..., 0].double()
    travelled = torch.cumsum(gap, dim=-1) / rate
    return torch.cat([torch.zeros_like(travelled[..., :1]), travelled[..., :-1]], dim=-1).float()


def twin_data(cfg: DictConfig, frames: int) -> Twins:
    """The training twins of the module docstring, `frames` long at the rig's rate."""
    e, views = cfg.model.evaluate, probe_views(cfg)
    names = resolve_camera_names(cfg.data.source.cameras)
    cameras, rate = (names if views else names[:1]), float(cfg.data.source.fps)
    world = rig_world(cfg, e.probe_seed, e.probe_clips, frames, cameras=cameras, **UNIFORM_MIX)
    rng = np.random.default_rng([int(e.probe_seed), TWIN_STREAM])
    out: dict[str, list] = {"frames": [], "displacement": [], "start": []}
    for i in tqdm(range(int(e.probe_clips)), desc="twin probe clips"):
        first, second, t0 = twin_actions(rng, world.simulated_actions(i).astype(np.float64), rate)
        rendered = [rig_world(cfg, e.probe_seed, i + 1, frames, cameras=cameras, scenario=Scenario(ego_actions=a),
                              **UNIFORM_MIX)[i].frames for a in (first, second)]  # (k, f, 3, H, W) each
        out["frames"].append(torch.from_numpy(np.stack(rendered)).transpose(1, 2))  # (2, f, k, 3, H, W)
        out["displacement"].append(displacement(first, second, rate))
        out["start"].append(t0 + 1)
    return Twins(torch.stack(out["frames"]), torch.stack(out["displacement"]), torch.tensor(out["start"]))


def train_twin_probe(data: Twins, steps: int, batch: int = 32, lr: float = 2e-3, seed: int = 0,
                     mirror: list[int] | None = None, progress: bool = True,
                     ) -> tuple[TwinDisplacementProbe, dict[str, float]]:
    """Fit the twin probe on random frames i ≥ start of random scenes (AdamW, cosine decay to lr/20; mirrored and
    brightness-jittered as the pair probe is, a mirror image leaving the displacement unchanged). Frames before the
    twins part read 0 by construction and teach nothing. Returns the probe in eval mode and its first/last loss."""
    generator = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    n, _, f, k = data.frames.shape[:4]
    if int(data.start.max()) >= f:
        raise ValueError(f"train_twin_probe: every scene needs a frame at which its twins differ (start < {f})")
    probe = TwinDisplacementProbe(cameras=k)
    optim = torch.optim.AdamW(probe.parameters(), lr=lr, weight_decay=1e-4)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optim, max(1, steps), eta_min=lr / 20)
    losses = []
    for _ in tqdm(range(steps), desc="twin probe", disable=not progress):
        scene = torch.randint(n, (batch,), generator=generator)
        start = data.start[scene]
        frame = start + (torch.rand(batch, generator=generator) * (f - start)).long()
        pair = to_float(data.frames[scene, :, frame])  # (b, 2, k, 3, H, W)
        pair, _ = augment_pairs(pair, torch.zeros(batch, 2), generator, [0] if k == 1 else mirror)
        loss = probe.loss(jitter(pair, generator), data.displacement[scene, frame])
        optim.zero_grad()
        loss.backward()
        optim.step()
        schedule.step()
        losses.append(float(loss.detach()))
    return probe.eval(), {"first_loss": float(np.mean(losses[:10])), "last_loss": float(np.mean(losses[-10:]))}


def probe_info(cfg: DictConfig, frames: int) -> dict[str, Any]:
    """What `twin_probe` trains on and reads (MUST_MATCH for a saved one to be loaded): the pair probe's info without
    the settings the twin probe does not use (it reads frames of two futures at one instant, from twins only)."""
    return {key: value for key, value in action_probe_info(cfg, frames).items()
            if key not in ("probe_stride", "probe_driven_share")}


def load_twin_probe(folder: str | Path, cfg: DictConfig, frames: int) -> tuple[TwinDisplacementProbe, dict[str, Any]]:
    """The twin probe saved in `folder`; FileNotFoundError or ValueError naming the file and the setting that does
    not fit this run (MUST_MATCH, or a probe trained on the world this run scores)."""
    views = probe_views(cfg)
    probe = TwinDisplacementProbe(cameras=len(views) if views else 1)
    saved = load_saved_probe(probe, Path(folder), (WEIGHTS, INFO), "twin_probe", probe_info(cfg, frames), MUST_MATCH,
                             int(cfg.context.seed))
    return probe.eval(), saved


def twin_probe(cfg: DictConfig, frames: int,
               save_to: str | Path | None = None) -> tuple[TwinDisplacementProbe | None, dict[str, Any] | None]:
    """The twin probe and its info for `speed_probe=twin` (`model.evaluate.twin_probe` loaded, or trained and, with
    `save_to`, saved there); (None, None) for `speed_probe=pair`."""
    if speed_probe(cfg) == "pair":
        return None, None
    folder = cfg.model.evaluate.get("twin_probe")
    if folder:
        probe, info = load_twin_probe(folder, cfg, frames)
        return probe, {**info, "loaded_from": str(folder)}
    e = cfg.model.evaluate
    probe, fit = train_twin_probe(twin_data(cfg, frames), int(e.probe_steps), seed=int(cfg.seed),
                                  mirror=probe_mirror(cfg))
    info = {**probe_info(cfg, frames), "fit": fit}
    if save_to is not None:
        save_action_probe(save_to, probe, info, (WEIGHTS, INFO))
    return probe, info


@torch.no_grad()
def probed_displacements(probe: TwinDisplacementProbe, low: torch.Tensor, high: torch.Tensor,
                         frames: list[int]) -> torch.Tensor:
    """(b, len(frames)) m the `high` futures' egos are ahead of the `low` ones' at `frames`; low, high (b, f, k, 3,
    H, W) (or (b, f, 3, H, W) for one camera)."""
    pairs = torch.stack([low[:, frames], high[:, frames]], dim=2)  # (b, n, 2, …)
    return probe(pairs.flatten(0, 1)).view(len(low), len(frames))


def twin_speed_row(probe: TwinDisplacementProbe, video: torch.Tensor, commanded: torch.Tensor, first: int,
                   stride: int, commands: int, pair: tuple[int, int], rate: float, draws: int = 1) -> dict[str, Any]:
    """The speed contrast error of a command-major batch read by the twin probe (module docstring), with 95 %
    intervals over contexts, in the layout of error_row's speed_contrast and realised speed_contrast.

    video (C·N·D, f, …) as error_row's; commanded (C·N, f, 2); first: the first generated frame t0; pair: the
    (high, low) commands of the speed contrast."""
    f = video.shape[1]
    scored = f - first - stride
    if scored < 1 or len(video) != len(commanded) * draws:
        raise ValueError(f"twin_speed_row: {len(video)} videos of {f} frames for {len(commanded)} commanded futures "
                         f"× {draws} draws, first generated frame {first}, stride {stride}")
    high, low = (video.unflatten(0, (commands, -1))[k] for k in pair)  # (N·D, f, …)
    ahead = probed_displacements(probe, low, high, [*range(first, first + stride), *range(f - stride, f)])
    realised = by_context((ahead[:, stride:].sum(1) - ahead[:, :stride].sum(1)) * rate / (scored * stride), draws)
    means = strided_actions(commanded, stride)[:, first + stride - 1 : -1, 0].mean(dim=1).unflatten(0, (commands, -1))
    wanted = means[pair[0]] - means[pair[1]]  # (N,)
    errors = (realised - wanted).abs()
    spread = float(realised.std()) if len(realised) > 1 else 0.0
    return {"speed_contrast": mean_interval(errors.tolist()).as_dict() | {"per_context": errors.tolist()},
            "realised": mean_interval(realised.tolist()).as_dict() | {
                "sd": spread, "commanded": float(wanted.mean()), "per_context": realised.tolist()}}


def read_speed_with_twins(rows: dict[str, dict[str, Any]], videos: dict[str, torch.Tensor],
                          probe: TwinDisplacementProbe, commanded: torch.Tensor, first: int, stride: int,
                          commands: int, pair: tuple[int, int], rate: float, draws: dict[str, int]) -> None:
    """Replace each row's speed contrast (error_row's, read by the pair probe) by the twin probe's reading, keeping
    the pair probe's as `speed_contrast_pair` (and realised `speed_contrast_pair`)."""
    for name, row in rows.items():
        twin = twin_speed_row(probe, videos[name], commanded, first, stride, commands, pair, rate, draws[name])
        row["speed_contrast_pair"], row["speed_contrast"] = row["speed_contrast"], twin["speed_contrast"]
        row["realised"]["speed_contrast_pair"] = row["realised"]["speed_contrast"]
        row["realised"]["speed_contrast"] = twin["realised"]
