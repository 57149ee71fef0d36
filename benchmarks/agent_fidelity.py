r"""Agent fidelity of a tokenizer: do the tokens keep the other road users? (GAIA-1 §7, GAIA-2 agents)

    python benchmarks/agent_fidelity.py --weights gaia1 --json outputs/agent_fidelity/gaia1.json
    python benchmarks/agent_fidelity.py --weights gaia2 --train-probe   # a probe of its own (written to --out)
    python benchmarks/agent_fidelity.py --weights <run>/checkpoints/last.ckpt --against gaia1   # side by side

On --clips held-out clips of a synthetic world used for nothing else (--world-seed), at the family's frame rate
(GAIA-1 6.25 Hz, GAIA-2 12.5 Hz), with that world's own instance masks, 2D boxes and lead agent
(gaia_app/eval/agent_fidelity.py):
- agent IoU of the segmentation probe on the real frames (the probe's ceiling: it should reach 0.6) and on the
  tokenizer's round trips, and `agent_iou_ratio` = tokenized ÷ real with a bootstrap interval over clips;
- PSNR (and LPIPS with --lpips-checkpoint: local VGG16 weights, optional --lpips-heads) inside the agents' boxes
  and on the background, real vs tokenized;
- lead-vehicle presence: of the frames with a vehicle within 30 m ahead in the ego lane, the share in which the
  probe covers at least half of it, on real and on tokenized frames.
Also the tokenizer's PSNR/SSIM (and LPIPS) on every video under --real-dir (real dashcam clips it never trained on).
With --against, a second tokenizer's round trips of the same clips are scored in the same run, and the difference of
the two ratios gets a paired bootstrap interval (the clips resampled once for both).

The probe is the shipped one (gaia_app/weights/probes, trained on 1 024 clips of world 4901), so every tokenizer is
scored by the same reader; --train-probe trains one on a world of its own (--probe-seed, --probe-clips scenes,
--probe-steps, the `sharp` recipe of `train_agent_probe`, 4 min on 2 cores) and writes it to OUT for --probe.
Target: agent_iou_ratio ≥ 0.8 for GAIA-1 and for GAIA-2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from gaia_app.data.clip import Clip
from gaia_app.data.datasets import fit_to_resolution
from gaia_app.data.synthetic import SyntheticClipDataset
from gaia_app.data.transforms import resample_clip, to_float
from gaia_app.data.video_io import read_video, video_info
from gaia_app.encoders.perceptual import load_perceptual
from gaia_app.eval.agent_fidelity import (
    FidelityFrames,
    fidelity_frames,
    finite_interval,
    iou_ratio,
    iou_ratio_by_frame,
    iou_ratio_difference,
    lead_found,
    lead_share,
    per_clip_overlap,
    per_frame_overlap,
    region_lpips,
    region_psnr,
)
from gaia_app.eval.agent_iou import load_agent_probe, predicted_agents, save_agent_probe, train_agent_probe
from gaia_app.eval.metrics import psnr, ssim
from gaia_app.models.probes import AgentSegmentationProbe
from gaia_app.weights.folders import load_nets, shipped_folder, weight_files
from gaia_app.weights.nets import checkpoint_nets

RATES = {"gaia1": 6.25, "gaia2": 12.5}  # each family's frame rate: GAIA-1 §3; the GAIA-2 weights' MANIFEST
PROBE_RATE = RATES["gaia1"]
SOURCE_FPS = 25.0
PROBE_WIDTHS = (16, 32, 64)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--weights", required=True, help="gaia1, gaia2, a folder of exported weights or a tokenizer .ckpt")
    p.add_argument("--against", default=None,
                   help="a second tokenizer of the same family, scored on the same clips in this run: its agent "
                        "scores and the paired difference of agent_iou_ratio (--weights minus --against)")
    p.add_argument("--json", type=Path, default=None, help="write the results here")
    p.add_argument("--out", type=Path, default=Path("outputs/agent_fidelity/probe"), help="where --train-probe writes")
    p.add_argument("--clips", type=int, default=64, help="held-out clips")
    p.add_argument("--frames", type=int, default=8,
                   help="frames per clip at the family's rate (a multiple of GAIA-2's τ = 4)")
    p.add_argument("--world-seed", type=int, default=4949, help="the held-out world (used for nothing else)")
    p.add_argument("--probe", default="probes", help="weights folder of the agent probe (default: the shipped one)")
    p.add_argument("--train-probe", action="store_true", help="train a probe on the probe world instead")
    p.add_argument("--probe-seed", type=int, default=4901, help="the probe's training world")
    p.add_argument("--probe-clips", type=int, default=1024)
    p.add_argument("--probe-steps", type=int, default=3000)
    p.add_argument("--real-dir", type=Path,
                   default=Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real")
    p.add_argument("--real-frames", type=int, default=16, help="frames per real video at the family's rate")
    p.add_argument("--lpips-checkpoint", type=Path, default=None, help="local VGG16 weights (torchvision layout)")
    p.add_argument("--lpips-heads", type=Path, default=None, help="local LPIPS heads (vgg.pth of PerceptualSimilarity)")
    args = p.parse_args(argv)
    if args.clips < 2 or args.frames < 4 or args.frames % 4:
        p.error(f"--clips must be ≥ 2 and --frames a multiple of 4, got {args.clips} and {args.frames}")
    return args


def labelled_world(seed: int, count: int, frames: int, rate: float, progress: str) -> FidelityFrames:
    """`count` clips of the synthetic world `seed` at 64 × 112, `frames` frames at `rate` Hz, with their labels."""
    clip_len = int(np.ceil((frames - 1) / rate * SOURCE_FPS)) + 1
    world = SyntheticClipDataset(num_clips=count, seed=seed, height=64, width=112, clip_len=clip_len, render_rate=rate)
    return fidelity_frames([world.sample(i) for i in tqdm(range(count), desc=progress)], rate, frames)


def agent_probe(args: argparse.Namespace) -> tuple[AgentSegmentationProbe, dict[str, Any]]:
    """The probe of the weights folder --probe (the shipped one by default), or with --train-probe one trained on
    the probe world and written to OUT (a folder --probe can name later)."""
    if not args.train_probe:
        probe, info = load_agent_probe(args.probe)
        return probe, {**info, "path": str(shipped_folder(args.probe))}
    train = labelled_world(args.probe_seed, args.probe_clips, args.frames, PROBE_RATE, "render the probe's world")
    probe, fit = train_agent_probe(train.frames, train.agents, steps=args.probe_steps, seed=0, sharp=True,
                                   widths=PROBE_WIDTHS)
    info = {**fit, "world_seed": args.probe_seed, "clips": args.probe_clips, "frames": args.frames,
            "rate": PROBE_RATE, "steps": args.probe_steps, "recipe": "train_agent_probe(sharp=True)"}
    save_agent_probe(probe, args.out, info)
    return probe, {**info, "path": str(args.out)}


def tokenizer_round_trip(weights: str) -> tuple[str, Any]:
    """(family, fn): fn maps videos (N, t, 3, H, W) in [-1, 1] to their reconstructions through the tokens.
    weights: a shipped name, a weights folder, or a tokenizer training checkpoint (.ckpt) of either family."""
    if Path(weights).suffix == ".ckpt":
        nets, _, family = checkpoint_nets(weights, ("tokenizer", "video_tokenizer"), "--weights")
        families = [family]
    else:
        folder = shipped_folder(weights)
        families = [c for c in ("tokenizer", "video_tokenizer") if _has(folder, c)]
        if not families:
            raise SystemExit(f"--weights {weights}: {folder} holds neither tokenizer.* (GAIA-1) nor video_tokenizer.* "
                             "(GAIA-2)")
        nets, _ = load_nets(folder, families[0])
    net = nets["net"]

    @torch.no_grad()
    def gaia1(video: torch.Tensor) -> torch.Tensor:
        flat = video.flatten(0, 1)
        out = torch.cat([net.decode(net.encode(chunk)).clamp(-1, 1) for chunk in flat.split(64)])
        return out.unflatten(0, video.shape[:2])

    @torch.no_grad()
    def gaia2(video: torch.Tensor) -> torch.Tensor:  # one camera: (N, 1, T, 3, H, W) through the video tokenizer
        return torch.cat([net.decode(net.encode(clip[None, None]).mode())[:, 0].clamp(-1, 1) for clip in video])

    return ("gaia1", gaia1) if families[0] == "tokenizer" else ("gaia2", gaia2)


def _has(folder: Path, component: str) -> bool:
    return all(path.is_file() for path in weight_files(folder, component))


def real_videos(root: Path, frames: int, rate: float) -> list[Clip]:
    """Every video under `root` at `rate` (or its own rate where that is lower), its first `frames` frames at
    64 × 112 (a whole number of τ = 4 steps)."""
    clips = []
    for path in sorted(p for p in root.rglob("*") if p.suffix.lower() in (".mp4", ".avi", ".mov", ".mkv")):
        pixels, fps = read_video(path, max_frames=int(np.ceil(frames * fps_ratio(path, rate))) + 4)
        stamps = np.arange(len(pixels)) / fps
        clip = Clip(str(path.relative_to(root)), pixels.transpose(0, 3, 1, 2)[None], stamps)
        # a source slower than the model's rate (PandaSet's 10 Hz for GAIA-2's 12.5 Hz) keeps its own frames
        clip = fit_to_resolution(resample_clip(clip, min(rate, fps)), 64, 112, "crop")
        keep = min(frames, clip.num_frames) // 4 * 4
        if keep:
            clips.append(clip.select_frames(np.arange(keep)))
    return clips


def fps_ratio(path: Path, rate: float) -> float:
    """Source frames per frame at `rate` (at least 1)."""
    return max(float(video_info(path).fps) / rate, 1.0)


def real_clip_rows(round_trip: Any, clips: list[Clip], lpips: Any) -> dict[str, dict[str, float]]:
    rows = {}
    for clip in tqdm(clips, desc="real videos"):
        video = to_float(torch.from_numpy(clip.frames[0]))[None]
        recon = round_trip(video)[0]
        row = {"frames": int(video.shape[1]), "fps": round(clip.fps, 2), "psnr": float(psnr(recon, video[0]).mean()),
               "ssim": float(ssim(recon, video[0]).mean())}
        if lpips is not None:
            row["lpips"] = float(lpips(recon, video[0]).mean())
        rows[clip.clip_id] = row
    return rows


def score(probe: AgentSegmentationProbe, held: FidelityFrames, tokenized: torch.Tensor, lpips: Any) -> dict[str, Any]:
    """Every number of the module docstring for real and tokenized frames."""
    predicted = {"real": predicted_agents(probe, held.frames), "tokenized": predicted_agents(probe, tokenized)}
    by_frame = {k: per_frame_overlap(v, held.agents) for k, v in predicted.items()}
    overlap = {k: (i.sum(1), u.sum(1)) for k, (i, u) in by_frame.items()}  # per clip: the frames' counts summed
    out: dict[str, Any] = {"agent_iou": {k: float(i.sum() / max(u.sum(), 1)) for k, (i, u) in overlap.items()}}
    out["agent_iou_ratio"] = iou_ratio(overlap["real"], overlap["tokenized"]).as_dict()
    out["agent_iou_ratio_by_frame"] = [e.as_dict() for e in iou_ratio_by_frame(by_frame["real"],
                                                                                by_frame["tokenized"])]
    background = ~held.boxes
    out["psnr_in_boxes"] = finite_interval(region_psnr(tokenized, held.frames, held.boxes)).as_dict()
    out["psnr_background"] = finite_interval(region_psnr(tokenized, held.frames, background)).as_dict()
    if lpips is not None:
        for name, region in (("lpips_in_boxes", held.boxes), ("lpips_background", background)):
            out[name] = finite_interval(region_lpips(lpips.distance_map, tokenized, held.frames, region)).as_dict()
    out["lead_presence"] = {k: lead_share(*lead_found(v, held.lead)).as_dict() for k, v in predicted.items()}
    out["lead_frames"] = int(held.lead.any(dim=(2, 3)).sum())
    return out


def markdown(family: str, result: dict[str, Any]) -> str:
    def est(d: dict[str, float], digits: int = 3) -> str:
        return f"{d['mean']:.{digits}f} [{d['low']:.{digits}f}, {d['high']:.{digits}f}]"

    s = result["scores"]
    lines = [f"Agent fidelity of the {family} tokenizer ({result['clips']} clips of world {result['world_seed']}, "
             f"{result['frames']} frames each at {result['rate']:g} Hz; 95 % intervals over clips)", "",
             "| | real frames | tokenized frames |", "|---|---|---|",
             f"| agent IoU (probe) | {s['agent_iou']['real']:.3f} | {s['agent_iou']['tokenized']:.3f} |",
             f"| lead vehicle found ({s['lead_frames']} frames) | {est(s['lead_presence']['real'])} | "
             f"{est(s['lead_presence']['tokenized'])} |", "",
             f"agent_iou_ratio (tokenized ÷ real): **{est(s['agent_iou_ratio'])}** (target ≥ 0.8)", "",
             "by frame of the clip: " + ", ".join(f"{e['mean']:.2f}" for e in s["agent_iou_ratio_by_frame"]), "",
             "| tokenized vs real | in agent boxes | background |", "|---|---|---|",
             f"| PSNR (dB) ↑ | {est(s['psnr_in_boxes'], 2)} | {est(s['psnr_background'], 2)} |"]
    if "lpips_in_boxes" in s:
        lines.append(f"| LPIPS ↓ | {est(s['lpips_in_boxes'])} | {est(s['lpips_background'])} |")
    if result["real_videos"]:
        lines += ["", "| real video (never trained on) | frames (Hz) | PSNR ↑ | SSIM ↑ |"
                  + (" LPIPS ↓ |" if "lpips_in_boxes" in s else ""),
                  "|---|---|---|---|" + ("---|" if "lpips_in_boxes" in s else "")]
        for name, row in result["real_videos"].items():
            extra = f" {row['lpips']:.3f} |" if "lpips" in row else ""
            lines.append(f"| {name} | {row['frames']} ({row['fps']:g}) | {row['psnr']:.2f} | "
                         f"{row['ssim']:.3f} |{extra}")
    return "\n".join(lines) + "\n"


def against_round_trip(args: argparse.Namespace, family: str) -> Any:
    """--against's round trip (None without it), refused before any work when its family is not --weights'."""
    if args.against is None:
        return None
    other_family, round_trip = tokenizer_round_trip(args.against)
    if other_family != family:
        raise SystemExit(f"--against {args.against} is a {other_family} tokenizer; "
                         f"--weights {args.weights} is {family}")
    return round_trip


def against(args: argparse.Namespace, round_trip: Any, probe: AgentSegmentationProbe, held: FidelityFrames,
            tokenized: torch.Tensor, lpips: Any) -> dict[str, Any]:
    """--against's tokenizer on the same clips: its scores and the paired difference of the two agent_iou_ratios."""
    other = round_trips(round_trip, held, f"{args.against} round trips")
    counts = [per_clip_overlap(predicted_agents(probe, frames), held.agents)
              for frames in (held.frames, tokenized, other)]
    return {"weights": args.against, "scores": score(probe, held, other, lpips),
            "agent_iou_ratio_difference": iou_ratio_difference(*counts).as_dict()}


def round_trips(round_trip: Any, held: FidelityFrames, desc: str) -> torch.Tensor:
    """The held-out frames (N, t, 3, H, W) through a tokenizer, 8 clips at a time."""
    return torch.cat([round_trip(v) for v in tqdm(held.frames.split(8), desc=desc)])


def against_markdown(result: dict[str, Any]) -> str:
    a, d = result["against"], result["against"]["agent_iou_ratio_difference"]
    r = a["scores"]["agent_iou_ratio"]
    return (f"\nagainst {a['weights']} on the same clips: agent_iou_ratio "
            f"{r['mean']:.3f} [{r['low']:.3f}, {r['high']:.3f}]; difference (--weights − --against, paired over "
            f"clips): **{d['mean']:+.3f} [{d['low']:+.3f}, {d['high']:+.3f}]**\n")


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = parse_args(argv)
    family, round_trip = tokenizer_round_trip(args.weights)
    other_round_trip = against_round_trip(args, family)
    lpips = None
    if args.lpips_checkpoint is not None:
        lpips = load_perceptual("vgg16", args.lpips_checkpoint, args.lpips_heads, config_key="--lpips-checkpoint")
    probe, probe_info = agent_probe(args)
    rate = RATES[family]
    held = labelled_world(args.world_seed, args.clips, args.frames, rate, "render the held-out world")
    tokenized = round_trips(round_trip, held, f"{family} round trips")
    result = {"weights": args.weights, "family": family, "clips": args.clips, "frames": args.frames, "rate": rate,
              "world_seed": args.world_seed, "probe": probe_info, "scores": score(probe, held, tokenized, lpips),
              "real_videos": real_clip_rows(round_trip, real_videos(args.real_dir, args.real_frames, rate), lpips)
              if args.real_dir.is_dir() else {}}
    result["agent_iou_ratio"] = result["scores"]["agent_iou_ratio"]["mean"]
    if other_round_trip is not None:
        result["against"] = against(args, other_round_trip, probe, held, tokenized, lpips)
    if result["scores"]["agent_iou"]["real"] < 0.6:
        print(f"warning: the probe reads agent IoU {result['scores']['agent_iou']['real']:.3f} on real frames, "
              "below its 0.6 ceiling target: train it longer or on more scenes", file=sys.stderr)
    print(markdown(family, result) + (against_markdown(result) if "against" in result else ""))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    return result


if __name__ == "__main__":
    main()
