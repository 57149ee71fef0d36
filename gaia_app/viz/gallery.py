"""README gallery pictures from `make demo` (or `make demo-train`) outputs.

    python -m gaia_app.viz.gallery outputs/demo --out docs/gallery

From `make demo` (a `showcase/` folder, gaia_app/tasks/showcase.py): its two labelled strips, `commands.png` (one
context steered four ways) and `prompts.png` (night, snow against no prompt), and a headless screenshot of
`showcase.rrd`. From `make demo-train`: for each rollout folder (`rollout_action`, `rollout_text`) a PNG of a few
frames of its `grid.mp4` (real clip | future 0 | future 1 …, one row per time, labelled), and a screenshot of the
action rollout's Rerun recording in the headless viewer (`rerun_rollout.png`; skipped with the reason where the
viewer cannot start, see gaia_app/viz/screenshot.py).
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from gaia_app.data.synthetic.gallery import label
from gaia_app.data.video_io import read_video
from gaia_app.utils.run_dir import atomic_write_bytes
from gaia_app.viz.screenshot import ViewerUnavailable, screenshot_recording

ROLLOUTS = ("rollout_action", "rollout_text")


def rollout_strip(run_dir: Path, rows: int = 3, scale: int = 2) -> np.ndarray:
    """(rows·H, W, 3) uint8 RGB: frames of `run_dir/grid.mp4` from the last context frame to the end, each row
    labelled with its time; nearest-neighbour upscaled by `scale` so the small demo frames stay crisp."""
    results = json.loads((run_dir / "results.json").read_text())
    grid, fps = read_video(run_dir / "grid.mp4")
    upsample = round((results["video_frames"] - 1)
                     / max(results["context_frames"] + results["generated_frames"] - 1, 1))
    start = max(results["context_frames"] - 1, 0) * upsample
    picks = np.linspace(start, len(grid) - 1, rows).round().astype(int)
    lines = []
    for index in picks:
        row = cv2.resize(grid[index], None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
        phase = "context" if index <= start and results["context_frames"] else "generated"
        label(row, f"t = {index / fps:.2f} s ({phase})", (0, 0))
        lines.append(row)
    return np.concatenate(lines, axis=0)


def write_png(path: Path, rgb: np.ndarray) -> None:
    ok, encoded = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise RuntimeError(f"PNG encoding failed for {path}")
    atomic_write_bytes(path, encoded.tobytes())


def showcase_gallery(showcase: Path, out: Path) -> list[Path]:
    """The showcase's strips as commands.png and prompts.png, and a screenshot of its recording."""
    written = []
    for panel in ("commands", "prompts"):
        image = cv2.imread(str(showcase / panel / "strip.png"))
        if image is None:
            raise FileNotFoundError(f"{showcase / panel / 'strip.png'} is missing or unreadable: run `make demo` first")
        written.append(out / f"{panel}.png")
        write_png(written[-1], cv2.cvtColor(image, cv2.COLOR_BGR2RGB))
    try:
        written.append(screenshot_recording(showcase / "showcase.rrd", out / "rerun_showcase.png", max_size=1280))
    except ViewerUnavailable as err:
        print(f"skipped the Rerun screenshot: {err}")
    return written


def make_gallery(demo_dir: Path, out: Path) -> list[Path]:
    """Write the gallery PNGs of `demo_dir` into `out`; returns the files written."""
    if (demo_dir / "showcase").is_dir():
        out.mkdir(parents=True, exist_ok=True)
        return showcase_gallery(demo_dir / "showcase", out)
    missing = [name for name in ROLLOUTS if not (demo_dir / name / "grid.mp4").is_file()]
    if missing:
        raise FileNotFoundError(f"{demo_dir} lacks {', '.join(missing)}/grid.mp4: run `make demo` first")
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name in ROLLOUTS:
        written.append(out / f"{name}.png")
        write_png(written[-1], rollout_strip(demo_dir / name))
    try:
        written.append(screenshot_recording(demo_dir / "rollout_action" / "rollout.rrd", out / "rerun_rollout.png",
                                            max_size=1280))
    except ViewerUnavailable as err:
        print(f"skipped the Rerun screenshot: {err}")
    return written


def main(argv: Sequence[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("demo_dir", type=Path, help="the `make demo` output folder (outputs/demo)")
    p.add_argument("--out", type=Path, default=Path("docs/gallery"), help="folder for the PNGs")
    args = p.parse_args(argv)
    for path in make_gallery(args.demo_dir, args.out):
        print(path)


if __name__ == "__main__":
    main()
