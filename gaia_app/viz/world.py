"""Rerun view of a driving clip in its world: every camera in a grid, the rig's frusta, agent 3D
boxes and the ego path in 3D, actions as scalars and captions as text, on the `frame` timeline.

Works for any `Clip`: the ego pose comes from `frame_meta[t]['ego_pose']` ([x, y, yaw], as the
synthetic world writes it) or, when absent, from integrating the actions (speed, curvature).

Entities (root "/world" by default):
    /world                      RIGHT_HAND_Z_UP, agent class colours
    /world/ego_path             LineStrips3D of the whole clip (static)
    /world/ego                  Transform3D ego → world per frame
    /world/ego/rig/<camera>     Transform3D camera → ego + Pinhole (static), image per frame
    /world/ego/rig/<camera>/boxes   Boxes2D per frame (frame_meta['boxes_2d'])
    /world/ego/agents           Boxes3D in the ego frame per frame
    /actions/speed, /actions/curvature   Scalars;   /text   TextLog captions

Command line, a synthetic clip into an .rrd file (open it with `rerun out.rrd`):
    python -m gaia_app.viz.world --rrd outputs/synthetic.rrd --frames 50 --cameras 5
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from gaia_app.data.clip import AGENT_CATEGORIES, Clip
from gaia_app.viz.blueprints import rig_blueprint
from gaia_app.viz.media import rgb_archetype

CATEGORY_COLOURS = [(66, 135, 245), (245, 166, 35), (140, 90, 200), (80, 200, 120), (235, 70, 70)]


def ego_poses(clip: Clip) -> np.ndarray:
    """(t, 3) ego poses x, y (m), yaw (rad) in the world: logged poses, else integrated actions."""
    logged = [m.get("ego_pose") if m else None for m in (clip.frame_meta or [None] * clip.num_frames)]
    if all(p is not None for p in logged):
        return np.asarray(logged, dtype=np.float64)
    poses = np.zeros((clip.num_frames, 3))
    if clip.actions is None:
        return poses
    dt = np.diff(clip.timestamps)
    for t in range(clip.num_frames - 1):
        speed, curvature = clip.actions[t]
        x, y, yaw = poses[t]
        turn = speed * dt[t] * curvature
        chord = speed * dt[t] * np.sinc(turn / (2 * np.pi))
        poses[t + 1] = x + chord * np.cos(yaw + turn / 2), y + chord * np.sin(yaw + turn / 2), yaw + turn
    return poses


def world_blueprint(camera_names: list[str], root: str = "/world") -> rrb.Blueprint:
    """Camera grid on top; 3D world, actions and captions below."""
    return rig_blueprint(camera_names, rig_origin=f"{root}/ego/rig", world_origin=root, scalars_origin="/actions",
                         text_origin="/text")


def _log_static(rec: rr.RecordingStream, clip: Clip, poses: np.ndarray, root: str) -> None:
    rec.log(root, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    rec.log(root, rr.AnnotationContext([(i, name, CATEGORY_COLOURS[i]) for i, name in enumerate(AGENT_CATEGORIES)]),
            static=True)
    path = np.c_[poses[:, :2], np.full(len(poses), 0.05)]
    rec.log(f"{root}/ego_path", rr.LineStrips3D([path], colors=[(255, 220, 0)], radii=[0.08]), static=True)
    for cam in clip.cameras or []:
        entity = f"{root}/ego/rig/{cam.name}"
        rec.log(entity, rr.Transform3D(translation=cam.extrinsics[:3, 3], mat3x3=cam.extrinsics[:3, :3]), static=True)
        rec.log(entity, rr.Pinhole(image_from_camera=cam.intrinsics, resolution=[cam.width, cam.height],
                                   camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=2.0), static=True)


def _log_agents(rec: rr.RecordingStream, clip: Clip, t: int, root: str) -> None:
    if clip.agents is None:
        return
    boxes = clip.agents[t]
    rec.log(f"{root}/ego/agents", rr.Boxes3D(
        centers=boxes.centre, half_sizes=boxes.size / 2,
        rotation_axis_angles=[rr.RotationAxisAngle(axis=[0, 0, 1], radians=float(y)) for y in boxes.yaw],
        class_ids=boxes.category, labels=[f"{AGENT_CATEGORIES[c]} {i}" for c, i in zip(boxes.category, boxes.track_id)],
        show_labels=False))


def _log_boxes_2d(rec: rr.RecordingStream, clip: Clip, t: int, root: str) -> None:
    per_camera = ((clip.frame_meta or [None] * clip.num_frames)[t] or {}).get("boxes_2d") or {}
    for name, boxes in per_camera.items():
        rec.log(f"{root}/ego/rig/{name}/boxes", rr.Boxes2D(
            array=np.array([b["box"] for b in boxes]).reshape(-1, 4), array_format=rr.Box2DFormat.XYXY,
            class_ids=[AGENT_CATEGORIES.index(b["category"]) for b in boxes],
            labels=[f"{b['category']} {b['track_id']}" for b in boxes], show_labels=False))


def log_world(rec: rr.RecordingStream, clip: Clip, *, root: str = "/world", frame_offset: int = 0,
              jpeg_quality: int | None = 90, send_blueprint: bool = True, series_root: str = "") -> None:
    """Log `clip` (frames, rig, agents, ego path, actions, captions) on the `frame` timeline
    starting at `frame_offset`. jpeg_quality None logs raw images. Actions and captions go to
    `{series_root}/actions` and `{series_root}/text` (several clips in one recording: one series_root each).
    The `frame` timeline is cleared afterwards so later logs on `rec` do not inherit the last frame."""
    names = [c.name for c in clip.cameras] if clip.cameras else [f"view{i}" for i in range(clip.num_views)]
    if send_blueprint:
        rec.send_blueprint(world_blueprint(names, root))
    poses = ego_poses(clip)
    _log_static(rec, clip, poses, root)
    for t in range(clip.num_frames):
        rec.set_time("frame", sequence=frame_offset + t)
        x, y, yaw = poses[t]
        rec.log(f"{root}/ego", rr.Transform3D(translation=[x, y, 0.0],
                                              rotation=rr.RotationAxisAngle(axis=[0, 0, 1], radians=float(yaw))))
        for v, name in enumerate(names):
            rec.log(f"{root}/ego/rig/{name}", rgb_archetype(np.ascontiguousarray(clip.frames[v, t].transpose(1, 2, 0)),
                                                            jpeg_quality))
        _log_boxes_2d(rec, clip, t, root)
        _log_agents(rec, clip, t, root)
        if clip.actions is not None:
            rec.log(f"{series_root}/actions/speed", rr.Scalars(float(clip.actions[t, 0])))
            rec.log(f"{series_root}/actions/curvature", rr.Scalars(float(clip.actions[t, 1])))
        if clip.text is not None and clip.text[t]:
            rec.log(f"{series_root}/text", rr.TextLog(clip.text[t]))
    rec.disable_timeline("frame")


def write_synthetic_recording(path: Path, seed: int = 0, height: int = 126, width: int = 224, cameras: int = 5,
                              frames: int = 50) -> None:
    """Generate a synthetic clip (urban, following traffic) and log it with log_world into `path`."""
    from gaia_app.data.synthetic import Scenario, generate_clip

    clip = generate_clip(seed=seed, height=height, width=width, cameras=cameras, clip_len=frames,
                         scenario=Scenario(environment="urban", behaviour="follow"))
    rec = rr.RecordingStream("gaia_synthetic", recording_id=clip.clip_id)
    rec.save(str(path))
    log_world(rec, clip)
    rec.flush()
    rec.disconnect()


def main(argv: Sequence[str] | None = None) -> None:
    p = argparse.ArgumentParser(description="Log a synthetic multi-camera clip to a Rerun .rrd file.")
    p.add_argument("--rrd", type=Path, required=True, help="output recording")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--height", type=int, default=126)
    p.add_argument("--width", type=int, default=224)
    p.add_argument("--cameras", type=int, default=5, help="1-5")
    p.add_argument("--frames", type=int, default=50)
    args = p.parse_args(argv)
    args.rrd.parent.mkdir(parents=True, exist_ok=True)
    write_synthetic_recording(args.rrd, args.seed, args.height, args.width, args.cameras, args.frames)


if __name__ == "__main__":
    main()
