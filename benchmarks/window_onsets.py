r"""How often a training window of a latent cache holds a command's onset in the steps a rollout generates, under each
way of drawing windows (`data.window_sampling`, gaia_app/data/latent_windows.py). Exact expectations from the
samplers' start probabilities, no draws.

A synthetic clip that leaves its policy (meta.open_loop) records when its command starts (meta.command_start_s). A
window of `steps` latent steps starting at step s "holds the onset in its generated steps" when that frame lies in
its steps from `change_after` on, the steps a rollout with `change_after` context steps generates: futures that must
start a turn or a brake the context does not show. The table also counts the windows whose last context step holds
the onset (the context shows its start: a latent step spans τ frames, so an onset within a step is split between
the two windows around it).

    python benchmarks/window_onsets.py --cache outputs/road_users/latents_s4 --steps 4 --change-after 2 --out onsets
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from gaia_app.data.clip import ClipError
from gaia_app.data.latent_cache import LatentClip, find_latent_clips, read_latent_clip
from gaia_app.data.latent_windows import WINDOW_SAMPLING, start_probabilities
from gaia_app.utils.run_dir import atomic_write_text

PLACES = {"generated steps": (0, None), "last context step": (-1, 0)}  # latent steps relative to change_after


def onset_step_mask(clip: LatentClip, steps: int, change_after: int,
                    place: str = "generated steps") -> np.ndarray | None:
    """(starts,) bool per window start: the clip's command onset lies in the window's `place` (PLACES: its generated
    steps, or its last context step, where the context shows part of the command); None for a policy clip.
    ClipError naming an open-loop clip without meta.command_start_s."""
    if not clip.meta.get("open_loop"):
        return None
    if "command_start_s" not in clip.meta:
        raise ClipError(f"latent clip '{clip.clip_id}': meta.open_loop without meta.command_start_s (encode the cache "
                        "again: the synthetic world records when its command starts)")
    onset = int(np.searchsorted(clip.timestamps, float(clip.meta["command_start_s"]) - 1e-6))
    tau, starts = clip.temporal_downsampling, np.arange(clip.mean.shape[1] - steps + 1)
    first, last = PLACES[place]
    end = starts + (steps if last is None else change_after + last)
    return ((starts + change_after + first) * tau <= onset) & (onset < end * tau)


def onset_shares(folders: list[Path], steps: int, change_after: int) -> dict[str, Any]:
    """{sampling: {place: {"all windows": share, "open-loop clips' windows": share}}} for each place of PLACES, plus
    the clip counts."""
    clips = [read_latent_clip(folder) for folder in folders]
    masks = {place: [onset_step_mask(clip, steps, change_after, place) for clip in clips] for place in PLACES}
    open_loop = [i for i, mask in enumerate(masks["generated steps"]) if mask is not None]
    shares: dict[str, Any] = {}
    for sampling in WINDOW_SAMPLING:
        weights = start_probabilities(clips, steps, sampling, change_after)
        shares[sampling] = {}
        for place, place_masks in masks.items():
            held = [0.0 if mask is None else float(w.numpy()[mask].sum()) for w, mask in zip(weights, place_masks)]
            shares[sampling][place] = {
                "all windows": float(np.mean(held)),
                "open-loop clips' windows": float(np.mean([held[i] for i in open_loop])) if open_loop else None}
    return {"clips": len(clips), "open_loop_clips": len(open_loop), "steps": steps, "change_after": change_after,
            "shares": shares}


def markdown(result: dict[str, Any]) -> str:
    lines = [f"{result['clips']} clips ({result['open_loop_clips']} open-loop), windows of {result['steps']} latent "
             f"steps, {result['change_after']} of them context", "",
             "| window sampling | " + " | ".join(f"onset in the {place}: all windows | of the open-loop clips' windows"
                                              for place in PLACES) + " |", "|---" + "|---:" * 2 * len(PLACES) + "|"]
    for sampling, by_place in result["shares"].items():
        cells = []
        for share in by_place.values():
            open_loop = share["open-loop clips' windows"]
            cells += [f"{share['all windows']:.3f}", "–" if open_loop is None else f"{open_loop:.3f}"]
        lines.append(f"| {sampling} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cache", type=Path, required=True, help="a latent cache root (its train/ split is read)")
    parser.add_argument("--steps", type=int, default=4, help="latent steps per window (data.steps)")
    parser.add_argument("--change-after", type=int, default=2, help="context steps of a rollout (data.change_after)")
    parser.add_argument("--out", type=Path, help="folder for window_onsets.{json,md}")
    args = parser.parse_args(argv)
    folders = find_latent_clips(args.cache / "train")
    if not folders:
        raise FileNotFoundError(f"--cache {args.cache}: no latent clips under train/")
    result = onset_shares(folders, args.steps, args.change_after)
    table = markdown(result)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(args.out / "window_onsets.json", json.dumps(result, indent=2))
        atomic_write_text(args.out / "window_onsets.md", table)
    print(table)
    return result


if __name__ == "__main__":
    main()
