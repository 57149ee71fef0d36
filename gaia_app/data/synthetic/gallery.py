"""Sample pictures of the synthetic world.

    python -m gaia_app.data.synthetic.gallery --png docs/synthetic_samples.png

The PNG is a grid: one row per (environment, weather, time of day, behaviour) setting, one
column per camera of the default five-camera rig, each row labelled. For a Rerun recording of a
clip use `python -m gaia_app.viz.world --rrd out.rrd` (data must not import viz).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from gaia_app.data.synthetic.generate import generate_clip
from gaia_app.data.synthetic.scenario import Scenario

GALLERY_ROWS = (
    ("urban", "clear", "day", "follow"), ("suburban", "clear", "dusk", "turn"),
    ("highway", "rain", "day", "lane_change"), ("rural", "fog", "day", "cruise"), ("urban", "snow", "day", "brake"),
    ("urban", "clear", "night", "cruise"), ("highway", "clear", "dusk", "follow"),
    ("suburban", "rain", "night", "accelerate"),
)
"""(environment, weather, time of day, behaviour) of each gallery row."""


def gallery_image(seed: int = 0, height: int = 126, width: int = 224, rows=GALLERY_ROWS) -> np.ndarray:
    """(rows·h, 5·w, 3) uint8 RGB grid of first frames, one labelled row per setting."""
    lines = []
    for k, (env, weather, tod, behaviour) in enumerate(rows):
        scenario = Scenario(environment=env, weather=weather, time_of_day=tod, behaviour=behaviour)
        clip = generate_clip(seed=seed + k, height=height, width=width, cameras=5, clip_len=1, scenario=scenario)
        row = np.concatenate(list(clip.frames[:, 0].transpose(0, 2, 3, 1)), axis=1).copy()
        label(row, f"{env}, {weather}, {tod}, {behaviour}", (0, 0))
        for v, cam in enumerate(clip.cameras):
            label(row, cam.name, (v * width, height - 13))
        lines.append(row)
    return np.concatenate(lines, axis=0)


def label(img: np.ndarray, text: str, corner: tuple[int, int]) -> None:
    """White text on a dark band at `corner` (x, y of the band's top left), in place."""
    (w, h), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.33, 1)
    x, y = corner
    img[y:y + h + 6, x:x + w + 6] = img[y:y + h + 6, x:x + w + 6] // 3
    cv2.putText(img, text, (x + 3, y + h + 2), cv2.FONT_HERSHEY_SIMPLEX, 0.33, (255, 255, 255), 1, cv2.LINE_AA)


def main(argv: Sequence[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--png", type=Path, required=True, help="write the sample grid here")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--height", type=int, default=126, help="tile height")
    p.add_argument("--width", type=int, default=224, help="tile width")
    args = p.parse_args(argv)
    args.png.parent.mkdir(parents=True, exist_ok=True)
    image = gallery_image(args.seed, args.height, args.width)
    cv2.imwrite(str(args.png), cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])


if __name__ == "__main__":
    main()
