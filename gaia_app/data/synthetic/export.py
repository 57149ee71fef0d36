"""Export synthetic clips to the clip-folder format (DESIGN.md §4).

    python -m gaia_app.data.synthetic.export --out data/synthetic --num-clips 100 --seed 0 \\
        --height 288 --width 512 --cameras front front_left front_right --clip-len 64 --fps 25

Clip i of the export equals SyntheticClipDataset(seed=S, ...)[i]; folders are named by clip id.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from tqdm import tqdm

from gaia_app.data.clip_writer import write_clip
from gaia_app.data.synthetic.dataset import SyntheticClipDataset


def parse_mix(text: str | None) -> dict[str, float] | None:
    """'clear=0.6,rain=0.4' → {'clear': 0.6, 'rain': 0.4}; None stays None."""
    if text is None:
        return None
    try:
        return {key.strip(): float(value) for key, value in (item.split("=") for item in text.split(",") if item)}
    except ValueError:
        raise ValueError(f"expected name=probability pairs separated by commas, got {text!r}") from None


def parse_cameras(values: Sequence[str]) -> int | list[str]:
    """A single number is a camera count (1–5); otherwise camera names."""
    return int(values[0]) if len(values) == 1 and values[0].isdigit() else list(values)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="root folder of the clip folders")
    p.add_argument("--num-clips", type=int, default=16)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--height", type=int, default=64)
    p.add_argument("--width", type=int, default=112)
    p.add_argument("--cameras", nargs="+", default=["front"], help="camera names, or one count 1-5")
    p.add_argument("--clip-len", type=int, default=64, help="frames per clip")
    p.add_argument("--fps", type=float, default=25.0)
    p.add_argument("--weather-mix", default=None, help="e.g. clear=0.55,rain=0.15,fog=0.15,snow=0.15")
    p.add_argument("--time-of-day-mix", default=None, help="e.g. day=0.6,dusk=0.2,night=0.2")
    p.add_argument("--agent-density", type=float, default=1.0)
    p.add_argument("--overwrite", action="store_true", help="replace clip folders that exist")
    return p


def export(out: Path, dataset: SyntheticClipDataset, overwrite: bool = False, progress: bool = True) -> list[Path]:
    """Write every clip of `dataset` under `out`; returns the clip folders."""
    out.mkdir(parents=True, exist_ok=True)
    return [write_clip(dataset[i], out, overwrite=overwrite)
            for i in tqdm(range(len(dataset)), desc="synthetic clips", unit="clip", disable=not progress)]


def main(argv: Sequence[str] | None = None) -> list[Path]:
    args = build_parser().parse_args(argv)
    dataset = SyntheticClipDataset(
        num_clips=args.num_clips, seed=args.seed, height=args.height, width=args.width,
        cameras=parse_cameras(args.cameras), clip_len=args.clip_len, fps=args.fps,
        weather_mix=parse_mix(args.weather_mix), time_of_day_mix=parse_mix(args.time_of_day_mix),
        agent_density=args.agent_density)
    return export(args.out, dataset, args.overwrite)


if __name__ == "__main__":
    main()
