"""Labels of the synthetic world agree with the scene: captions, lead agent, lights, 3D/2D boxes."""

from __future__ import annotations

import re

import numpy as np
import pytest

from gaia_app.data.synthetic import AgentSpec, Junction, Scenario, Straight, SyntheticClipDataset, generate_clip
from gaia_app.data.synthetic.rig import project_points
from gaia_app.data.synthetic.world import Ego

FRONT_BUMPER = Ego.front


def test_night_captions_say_night_and_weather() -> None:
    for seed in range(4):
        clip = generate_clip(seed=seed, clip_len=3, scenario=Scenario(time_of_day="night", weather="snow"))
        assert all("night" in text.lower() and "snow" in text.lower() for text in clip.text), clip.text


@pytest.fixture(scope="module")
def bus_clip():
    """The ego follows a bus 15 m ahead on a straight road, at the bus's speed."""
    scenario = Scenario(environment="rural", country="DE", weather="clear", time_of_day="day", road=(Straight(700.0),),
                        lanes=2, ego_lane=0, ego_speed=12.0, behaviour="follow",
                        agents=(AgentSpec("bus", gap=15.0, speed=12.0),))
    return generate_clip(seed=6, height=96, width=168, clip_len=10, scenario=scenario)


def test_lead_bus_distance_in_caption_matches_ground_truth(bus_clip) -> None:
    for text, meta in zip(bus_clip.text, bus_clip.frame_meta):
        lead = meta["lead_agent"]
        assert lead["category"] == "bus" and lead["distance"] == pytest.approx(15.0, abs=1.0)
        numbers = [int(n) for n in re.findall(r"(\d+) meters", text)]
        assert "bus" in text and numbers == [round(lead["distance"])], text


def test_lead_distance_agrees_with_the_3d_box(bus_clip) -> None:
    """The lead gap is bumper to bumper: box centre x − half length − front bumper (straight road)."""
    for boxes, meta in zip(bus_clip.agents, bus_clip.frame_meta):
        i = int(np.flatnonzero(boxes.track_id == meta["lead_agent"]["track_id"])[0])
        gap = boxes.centre[i, 0] - boxes.size[i, 0] / 2 - FRONT_BUMPER
        assert gap == pytest.approx(meta["lead_agent"]["distance"], abs=0.05)
        assert abs(boxes.centre[i, 1]) < 0.2 and abs(boxes.yaw[i]) < 0.01  # straight ahead, same heading


def test_2d_boxes_contain_the_projected_3d_box_centres(bus_clip) -> None:
    cam = bus_clip.cameras[0]
    for boxes, meta in zip(bus_clip.agents, bus_clip.frame_meta):
        by_id = {b["track_id"]: b["box"] for b in meta["boxes_2d"]["front"]}
        uv, depth = project_points(cam, boxes.centre)
        for track, (u, v), z in zip(boxes.track_id, uv, depth):
            inside = z > 0 and 0 <= u < cam.width and 0 <= v < cam.height
            if inside:
                x0, y0, x1, y1 = by_id[int(track)]
                assert x0 <= u <= x1 and y0 <= v <= y1


def test_traffic_light_state_and_captions_agree() -> None:
    """A red light 25 m ahead: the ego brakes, the metadata reports it, the caption says red."""
    scenario = Scenario(environment="urban", country="DE", weather="clear", time_of_day="day", agents=(),
                        road=(Straight(130.0), Junction(traffic_light=True), Straight(300.0)), traffic_light="red",
                        ego_speed=10.0, behaviour="cruise", lanes=1)
    clip = generate_clip(seed=0, clip_len=25, fps=10.0, scenario=scenario)
    for text, meta in zip(clip.text, clip.frame_meta):
        assert meta["traffic_light"] == "red" and meta["intersection"] == "four_way"
        assert "red" in text
    assert clip.actions[-1, 0] < clip.actions[0, 0] - 3.0  # it slows down for the light
    distances = [m["traffic_light_distance"] for m in clip.frame_meta]
    assert np.all(np.diff(distances) <= 0) and distances[-1] > 0  # approaching and stopping before the line


def test_clip_meta_describes_the_scene() -> None:
    ds = SyntheticClipDataset(num_clips=6, seed=2, clip_len=2)
    for i in range(len(ds)):
        meta = ds[i].meta
        assert meta["weather"] in ("clear", "rain", "fog", "snow") and meta["time_of_day"] in ("day", "dusk", "night")
        assert meta["country"] in ("DE", "FR", "NL", "US", "GB", "JP") and 20 < meta["speed_limit"] <= 130
        assert set(meta["lane_types"]) <= {"solid", "dashed", "double_solid", "none"}
        assert meta["drive_side"] == ("left" if meta["country"] in ("GB", "JP") else "right")
