"""Import a PandaSet sequence (six cameras, ego motion, 3D agents) into one multi-camera clip folder.

    python -m gaia_app.data.importers.pandaset ../shared/data/real/pandaset_002 --out data/clips

Expected layout (as in shared/data/real/pandaset_002, see its README): `video_<w>x<h>/<camera>.mp4`,
`calib_and_poses/<camera>/{intrinsics,poses,timestamps}.json` (intrinsics for the original
1920×1080 images; poses camera→world), `meta/{timestamps,gps}.json`, `annotations/cuboids.jsonl`
(world-frame boxes).

Ego frame, per frame: origin at the front camera's optical centre; x forward = the front camera's
viewing direction projected onto the ground plane; z up = world z (PandaSet's world frame is
z-up); y = z × x (left). Roll and pitch of the car body are thus ignored, and "forward" is the
front camera's heading, which is mounted along the car's axis (within about a degree). Agent z
is therefore relative to the camera height (about 1.8 m above the road), not to the road.

Clip time is the frame time of `meta/timestamps.json` (the LiDAR sweep at which boxes and GPS
are given); each camera exposes within ±0.1 s of it, which the ego pose interpolation accounts
for when deriving the rig extrinsics.
"""

from __future__ import annotations

import argparse
import json
import logging
from collections import Counter
from pathlib import Path

import numpy as np
from tqdm import tqdm

from gaia_app.data.actions import curvature_from_poses, quaternion_to_rotation, unwrap_yaw, yaw_from_rotation
from gaia_app.data.clip import AGENT_CATEGORIES, AgentBoxes, CameraSpec, ClipError
from gaia_app.data.clip_writer import ClipFolderWriter, label_rows, meta_json
from gaia_app.data.transforms import plan_resize, resize_camera, resize_image
from gaia_app.data.video_io import iter_frames, video_info

log = logging.getLogger(__name__)

CAMERAS: tuple[str, ...] = ("front_camera", "front_left_camera", "front_right_camera", "left_camera",
                            "right_camera", "back_camera")
"""PandaSet camera folders; the clip names each view without the `_camera` suffix."""
ORIGINAL_SIZE = (1920, 1080)
"""(width, height) of the original PandaSet images, for which intrinsics.json is given."""

CATEGORY_MAP: dict[str, str] = {
    "Car": "car",
    "Pickup Truck": "car",  # a light vehicle, sized and driven like a car
    "Emergency Vehicle": "car",
    "Medium-sized Truck": "truck",
    "Semi-truck": "truck",
    "Other Vehicle - Construction Vehicle": "truck",
    "Bus": "bus",
    "Tram / Subway": "bus",
    "Bicycle": "cyclist",
    "Motorcycle": "cyclist",  # two-wheeler; the GAIA categories have no motorcycle
    "Motorized Scooter": "cyclist",
    "Personal Mobility Device": "cyclist",
    "Other Vehicle - Pedicab": "cyclist",
    "Pedestrian": "pedestrian",
    "Pedestrian with Object": "pedestrian",
}
"""PandaSet cuboid category → AGENT_CATEGORIES name. Categories not listed (cones, signs, barriers,
towed objects, animals, trains, uncommon vehicles) are dropped and counted in the log and in the
clip's metadata (`dropped_agents`)."""


def _load(path: Path):
    if not path.is_file():
        raise ClipError(f"{path}: missing (is this a PandaSet sequence folder?)")
    return json.loads(path.read_text())


def _camera_poses(seq: Path, camera: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera→world rotations (t, 3, 3), positions (t, 3) m, and exposure times (t,) s."""
    poses = _load(seq / "calib_and_poses" / camera / "poses.json")
    quats = np.array([[p["heading"][k] for k in "wxyz"] for p in poses])
    positions = np.array([[p["position"][k] for k in "xyz"] for p in poses])
    times = np.asarray(_load(seq / "calib_and_poses" / camera / "timestamps.json"), dtype=np.float64)
    return quaternion_to_rotation(quats), positions, times


def _interp(tq: np.ndarray, t: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Piecewise-linear interpolation of values (t, ...) at tq (k,), extrapolating linearly past the ends."""
    i = np.clip(np.searchsorted(t, tq) - 1, 0, len(t) - 2)
    w = ((tq - t[i]) / (t[i + 1] - t[i])).reshape(-1, *[1] * (values.ndim - 1))
    return values[i] * (1 - w) + values[i + 1] * w


class EgoTrack:
    """Ego poses from the front camera's track (module docstring: ego frame definition)."""

    def __init__(self, rotations: np.ndarray, positions: np.ndarray, times: np.ndarray) -> None:
        self.times = times
        self.positions = positions  # (t, 3) m, world
        self.yaw = unwrap_yaw(yaw_from_rotation(rotations, forward_axis=(0.0, 0.0, 1.0)))  # (t,) rad

    def at(self, tq: np.ndarray) -> np.ndarray:
        """Ego→world transforms (k, 4, 4) at times tq (k,) s."""
        pos, yaw = _interp(tq, self.times, self.positions), _interp(tq, self.times, self.yaw)
        c, s = np.cos(yaw), np.sin(yaw)
        pose = np.tile(np.eye(4), (len(tq), 1, 1))
        pose[:, 0, 0], pose[:, 0, 1], pose[:, 1, 0], pose[:, 1, 1] = c, -s, s, c
        pose[:, :3, 3] = pos
        return pose


def _mean_rigid(transforms: np.ndarray) -> np.ndarray:
    """The rigid transform (4, 4) closest to the mean of transforms (k, 4, 4): mean translation,
    mean rotation projected back onto a rotation by SVD."""
    u, _, vt = np.linalg.svd(transforms[:, :3, :3].mean(axis=0))
    rot = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rot, transforms[:, :3, 3].mean(axis=0)
    return out


def _camera_spec(seq: Path, camera: str, ego: EgoTrack, video_size: tuple[int, int]) -> CameraSpec:
    """Intrinsics scaled to the video, extrinsics camera→ego averaged over the sequence (a rigid rig)."""
    k = _load(seq / "calib_and_poses" / camera / "intrinsics.json")
    intrinsics = [[k["fx"], 0.0, k["cx"]], [0.0, k["fy"], k["cy"]], [0.0, 0.0, 1.0]]
    rotations, positions, times = _camera_poses(seq, camera)
    cam_to_world = np.tile(np.eye(4), (len(times), 1, 1))
    cam_to_world[:, :3, :3], cam_to_world[:, :3, 3] = rotations, positions
    # The ego pose at this camera's own exposure times, so the rig comes out rigid while driving.
    cam_to_ego = np.linalg.inv(ego.at(times)) @ cam_to_world
    name = camera.removesuffix("_camera")
    spec = CameraSpec(name, intrinsics, _mean_rigid(cam_to_ego), *ORIGINAL_SIZE)
    return spec.resized(*video_size)


def _track_ids(frames: list[list[dict]]) -> dict[str, int]:
    """PandaSet's string track ids → stable ints, numbered by first appearance."""
    ids: dict[str, int] = {}
    for boxes in frames:
        for box in boxes:
            ids.setdefault(box["track_id"], len(ids))
    return ids


def _agents(frames: list[list[dict]], ego_poses: np.ndarray) -> tuple[list[AgentBoxes], Counter]:
    """World-frame cuboids per frame → AgentBoxes in each frame's ego frame, and the dropped-category counts."""
    ids, dropped, out = _track_ids(frames), Counter(), []
    for boxes, pose in zip(frames, ego_poses):
        kept = [b for b in boxes if b["category"] in CATEGORY_MAP]
        dropped.update(b["category"] for b in boxes if b["category"] not in CATEGORY_MAP)
        centre_world = np.array([b["center"] for b in kept]).reshape(-1, 3)
        centre = (centre_world - pose[:3, 3]) @ pose[:3, :3]  # R^T (p - t), row vectors
        # PandaSet yaw 0 points the box length along world +y, so the heading is yaw + π/2.
        heading = np.array([b["yaw"] for b in kept]) + np.pi / 2 - np.arctan2(pose[1, 0], pose[0, 0])
        out.append(AgentBoxes(
            centre=centre,
            size=[[b["size"][1], b["size"][0], b["size"][2]] for b in kept],  # (w, l, h) -> (l, w, h)
            yaw=np.angle(np.exp(1j * heading)),  # wrap to (-π, π]
            category=[AGENT_CATEGORIES.index(CATEGORY_MAP[b["category"]]) for b in kept],
            track_id=[ids[b["track_id"]] for b in kept],
        ))
    return out, dropped


def _ego_motion(seq: Path, ego: EgoTrack, frame_times: np.ndarray) -> np.ndarray:
    """Actions (t, 2) at frame times: GPS speed (m/s) and curvature (1/m) from the front camera's heading."""
    gps = _load(seq / "meta" / "gps.json")
    speed = np.hypot([g["xvel"] for g in gps], [g["yvel"] for g in gps])
    kappa = curvature_from_poses(ego.positions[:, :2], ego.times, yaw=ego.yaw)
    return np.stack([speed, np.interp(frame_times, ego.times, kappa)], axis=1)


def _find_videos(seq: Path) -> Path:
    folders = sorted(seq.glob("video_*"))
    if not folders:
        raise ClipError(f"{seq}: no video_<w>x<h>/ folder with the camera mp4s")
    return folders[0]


def import_pandaset(
    seq_dir: str | Path,
    out_root: str | Path,
    *,
    clip_id: str | None = None,
    height: int | None = None,
    width: int | None = None,
    resize_mode: str = "crop",
    overwrite: bool = False,
    progress: bool = True,
) -> Path:
    """Import one PandaSet sequence as the clip folder `<out_root>/<clip_id>`.

    clip_id defaults to the sequence folder's name, prefixed `pandaset_` unless it has it.

    Six views (front, front_left, front_right, left, right, back) with intrinsics and camera→ego
    extrinsics; actions = (GPS speed m/s, curvature 1/m from the ego heading); agents in the ego
    frame. height/width (pixels, both or neither) re-encode the videos at that size with
    `resize_mode`; without them the mp4s are copied unchanged. Returns the clip folder.
    """
    if (height is None) != (width is None):
        raise ValueError("give both height and width, or neither")
    seq = Path(seq_dir)
    frame_times = np.asarray(_load(seq / "meta" / "timestamps.json"), dtype=np.float64)
    ego = EgoTrack(*_camera_poses(seq, "front_camera"))
    video_dir = _find_videos(seq)
    infos = {cam: video_info(video_dir / f"{cam}.mp4") for cam in CAMERAS}
    for cam, info in infos.items():
        if info.num_frames != len(frame_times):
            raise ClipError(f"{video_dir / cam}.mp4: {info.num_frames} frames, "
                            f"{seq / 'meta' / 'timestamps.json'} has {len(frame_times)}")
    specs = [_camera_spec(seq, cam, ego, (infos[cam].width, infos[cam].height)) for cam in CAMERAS]
    cuboids = [json.loads(line)["boxes"] for line in (seq / "annotations" / "cuboids.jsonl").read_text().splitlines()]
    agents, dropped = _agents(cuboids, ego.at(frame_times))
    if dropped:
        log.info("%s: dropped %d boxes of categories outside %s: %s", seq, sum(dropped.values()), AGENT_CATEGORIES,
                 ", ".join(f"{k} {v}" for k, v in dropped.most_common()))
    fps = float(1.0 / np.median(np.diff(frame_times)))
    first_fix = _load(seq / "meta" / "gps.json")[0]
    metadata = {"dataset": "pandaset", "sequence": seq.name, "country": "US",  # PandaSet is recorded in California
                "start_time_unix_s": float(frame_times[0]), "dropped_agents": dict(dropped),
                # [lat, lon] of the first frame: geofenced validation splits (data.val_region)
                "gps_start": [float(first_fix["lat"]), float(first_fix["long"])]}
    default_id = seq.name if seq.name.startswith("pandaset") else f"pandaset_{seq.name}"
    with ClipFolderWriter(out_root, clip_id or default_id, overwrite=overwrite) as writer:
        if height is None:
            for cam in tqdm(CAMERAS, desc="copy videos", disable=not progress):
                writer.copy_video(cam.removesuffix("_camera"), video_dir / f"{cam}.mp4")
        else:
            specs = _write_resized(writer, video_dir, specs, height, width, resize_mode, fps, progress)
        writer.write_labels(label_rows(frame_times - frame_times[0], _ego_motion(seq, ego, frame_times), agents=agents))
        writer.write_meta(meta_json(fps, specs, [s.name for s in specs], metadata))
    return writer.target


def _write_resized(writer: ClipFolderWriter, video_dir: Path, specs: list[CameraSpec], height: int,
                   width: int, mode: str, fps: float, progress: bool) -> list[CameraSpec]:
    """Re-encode each camera at (height, width), streaming; returns the specs with intrinsics updated."""
    out = []
    for cam, spec in zip(CAMERAS, specs):
        plan = plan_resize(spec.width, spec.height, width, height, mode)
        frames = tqdm(iter_frames(video_dir / f"{cam}.mp4"), desc=cam, unit="frame", disable=not progress)
        writer.write_video(spec.name, (resize_image(f, plan) for f in frames), fps)
        out.append(resize_camera(spec, plan))
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("seq_dir", help="PandaSet sequence folder (e.g. ../shared/data/real/pandaset_002)")
    parser.add_argument("--out", required=True, help="root folder of the clip folders")
    parser.add_argument("--clip-id", help="clip folder name (default: pandaset_<sequence>)")
    parser.add_argument("--height", type=int, help="re-encode at this height in pixels (with --width)")
    parser.add_argument("--width", type=int, help="re-encode at this width in pixels (with --height)")
    parser.add_argument("--resize-mode", choices=("crop", "stretch"), default="crop")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing clip folder")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    print(import_pandaset(args.seq_dir, args.out, clip_id=args.clip_id, height=args.height, width=args.width,
                          resize_mode=args.resize_mode, overwrite=args.overwrite))


if __name__ == "__main__":
    main()
