"""Run- and place-level validation splits (issue 24, item 4; GAIA-1 §3 holds out whole drives and geofenced
regions): segments of one drive never land on both sides."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gaia_app.data.clip_folder import ClipFolderDataset
from gaia_app.data.datamodules import split_by_clip, split_by_run
from gaia_app.data.importers.dashcam import import_dashcam
from gaia_app.data.video_io import write_video
from tests.conftest import compose_config

# four drives in two cities: (name, latitude, longitude)
DRIVES = [("london_a", 51.50, -0.12), ("london_b", 51.52, -0.10), ("paris_a", 48.85, 2.35), ("paris_b", 48.86, 2.34)]
PARIS = [48.0, 49.5, 1.5, 3.0]


@pytest.fixture(scope="module")
def clip_root(tmp_path_factory) -> Path:
    """Each drive: 2 s of video cut into four 0.5 s clips, with a GPS + speed log (its position in meta.json)."""
    from tests.data.conftest import smooth_frames

    tmp = tmp_path_factory.mktemp("drives")
    for k, (name, lat, lon) in enumerate(DRIVES):
        video = write_video(tmp / f"{name}.mp4", smooth_frames(60, 32, 48, k), fps=30)
        t = np.arange(0, 2.05, 0.1)
        rows = [f"{a:.2f},{lat + 1e-5 * a:.7f},{lon:.7f},{8.0:.1f},0.0" for a in t]
        log = tmp / f"{name}.csv"
        log.write_text("t,lat,lon,speed,curvature\n" + "\n".join(rows) + "\n")
        import_dashcam(video, tmp / "clips", clip_len_s=0.5, telemetry=log, progress=False)
    return tmp / "clips"


def drives(subset) -> set[str]:
    return {subset.dataset.describe(i)["source_video"] for i in subset.indices}


@pytest.mark.parametrize("seed", range(6))
def test_no_drive_is_on_both_sides(clip_root: Path, seed: int) -> None:
    source = ClipFolderDataset(clip_root)
    assert len(source) == 16
    train, val = split_by_run(source, val_fraction=0.25, seed=seed)
    assert not drives(train) & drives(val) and len(drives(val)) == 1
    assert sorted(train.indices + val.indices) == list(range(16))


def test_a_clip_split_would_mix_drives(clip_root: Path) -> None:
    """Why the split is by run: a random clip split puts segments of one drive on both sides."""
    source = ClipFolderDataset(clip_root)
    mixed = [bool(drives(t) & drives(v)) for t, v in (split_by_clip(source, 0.25, seed) for seed in range(6))]
    assert any(mixed)


def test_a_geofence_holds_out_every_drive_inside_it(clip_root: Path) -> None:
    source = ClipFolderDataset(clip_root)
    assert source.describe(0)["gps_start"][0] == pytest.approx(51.50, abs=1e-3)
    train, val = split_by_run(source, 0.25, 0, val_region=PARIS)
    assert drives(val) == {"paris_a.mp4", "paris_b.mp4"} and drives(train) == {"london_a.mp4", "london_b.mp4"}
    with pytest.raises(ValueError, match="holds 0 of 4 runs"):
        split_by_run(source, 0.25, 0, val_region=[0.0, 1.0, 0.0, 1.0])


def test_split_settings_are_checked(clip_root: Path, tmp_path: Path) -> None:
    from hydra.utils import instantiate

    base = ["data=video_folder", f"data.source.root={clip_root}", "data.height=32", "data.width=48", "data.fps=null",
            "data.clip_len=4", "data.num_workers=0"]
    datamodule = instantiate(compose_config("train", [*base, f"data.val_region={PARIS}"], tmp_path).data)
    datamodule.setup("fit")
    assert drives(datamodule.val_clips) == {"paris_a.mp4", "paris_b.mp4"}
    with pytest.raises(Exception, match="set data.split_by=run"):  # hydra wraps the ValueError
        instantiate(compose_config("train", [*base, "data.split_by=clip", f"data.val_region={PARIS}"], tmp_path).data)
    one = ClipFolderDataset(clip_root)
    one.clip_ids = [c for c in one.clip_ids if c.startswith("london_a")]
    with pytest.raises(ValueError, match="come from 1 run"):
        split_by_run(one, 0.25, 0)
