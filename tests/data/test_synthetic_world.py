"""World dynamics without rendering: light cycles, lane following, gaps, lane changes, braking,
stopping at red lights, pedestrians on crossings."""

from __future__ import annotations

import numpy as np
import pytest

from gaia_app.data.synthetic import Junction, Scenario, Straight
from gaia_app.data.synthetic.generate import WorldConfig
from gaia_app.data.synthetic.planning import make_plan
from gaia_app.data.synthetic.scenario import draw_setting
from gaia_app.data.synthetic.simulate import simulate
from gaia_app.data.synthetic.world import AMBER_SECONDS, PEDESTRIAN, LightCycle


def run(seed: int, scenario: Scenario, frames: int, fps: float = 10.0):
    rng = np.random.default_rng(seed)
    config = WorldConfig.make(clip_len=frames, fps=fps)
    setting = draw_setting(rng, scenario, config.weather_mix, config.time_of_day_mix)
    plan = make_plan(rng, scenario, setting, frames, fps, 1.5)
    return plan, simulate(plan, frames, fps)


def test_light_cycle_order_and_cross_phase() -> None:
    cycle = LightCycle(green=10.0, offset=0.0)
    times = np.arange(0.0, cycle.period, 0.5)
    own = [cycle.state(t) for t in times]
    assert own[0] == "green" and own[int(10.0 / 0.5)] == "amber" and own[int((10.0 + AMBER_SECONDS) / 0.5)] == "red"
    for t in times:  # never green for both roads
        assert not (cycle.state(t) == "green" and cycle.state(t, cross=True) == "green")
    assert LightCycle.starting(12.0, "red", 2.0).state(0.0) == "red"


@pytest.fixture(scope="module")
def busy_road():
    """20 s of dense traffic on a long straight four-lane road."""
    scenario = Scenario(environment="highway", road=(Straight(1500.0),), lanes=4, behaviour="cruise")
    return run(1, scenario, frames=200)


def test_vehicles_keep_their_gaps_and_lanes(busy_road) -> None:
    plan, states = busy_road
    a, geo = plan.world.agents, plan.layout.geometry
    same_way = np.flatnonzero((a.category != PEDESTRIAN) & (a.direction == 1) & (a.path == 0))
    centres = np.abs(geo.lane_offset(np.arange(geo.lanes)))
    for state in states[::10]:
        s, d = state.agents.s[same_way], state.agents.d[same_way]
        off_centre = np.min(np.abs(np.abs(d)[:, None] - centres[None]), axis=1)
        changing = (a.lane_change_progress(state.t)[same_way] > 0) & (a.lane_change_progress(state.t)[same_way] < 1)
        assert np.all(off_centre[~changing] < 0.05)
        for lane in centres:
            in_lane = np.flatnonzero(np.abs(np.abs(d) - lane) < 0.5)
            order = in_lane[np.argsort(s[in_lane])]
            gaps = np.diff(s[order]) - (a.size[same_way][order][1:, 0] + a.size[same_way][order][:-1, 0]) / 2
            assert np.all(gaps > 0.5)  # no vehicle drives into another


def test_traffic_changes_lanes_and_brakes(busy_road) -> None:
    plan, states = busy_road
    a = plan.world.agents
    assert np.sum(np.isfinite(a.change_t0) & (a.change_t0 > 0)) >= 2
    assert any(state.agents.braking.any() for state in states)
    assert any(state.agents.indicator.any() for state in states)
    speeds = np.array([state.agents.speed for state in states])
    moving = (a.category != PEDESTRIAN) & ~a.parked
    assert np.ptp(speeds[:, moving].mean(axis=0)) > 5.0  # agents have their own speeds


def test_traffic_stops_at_a_red_light() -> None:
    scenario = Scenario(environment="urban", road=(Straight(200.0), Junction(traffic_light=True), Straight(400.0)),
                        traffic_light="red", ego_speed=0.0, behaviour="cruise", lanes=2)
    plan, states = run(2, scenario, frames=60)
    site = plan.layout.junctions[0]
    a = plan.world.agents
    approaching = np.flatnonzero((a.category != PEDESTRIAN) & (a.direction == 1) & (a.path == 0) & ~a.parked)
    for state in states:
        if state.lights[0] != "red":
            continue
        fronts = state.agents.s[approaching] + a.size[approaching, 0] / 2
        before = fronts < site.stop_s + 1.0
        assert np.all(fronts[before] < site.stop_s + 0.5)  # nobody crosses the line while red
    last = states[-1]
    waiting = approaching[(last.agents.s[approaching] < site.stop_s) & (last.agents.s[approaching] > site.stop_s - 30)]
    if states[-1].lights[0] == "red" and len(waiting):
        assert last.agents.speed[waiting].min() < 0.5


def test_pedestrians_cross_at_zebra_crossings() -> None:
    scenario = Scenario(environment="urban", road=(Straight(160.0, crossing=True), Straight(500.0)), lanes=1)
    plan, states = run(4, scenario, frames=150)
    a = plan.world.agents
    crossers = np.flatnonzero((a.category == PEDESTRIAN) & (np.abs(states[0].agents.s - 80.0) < 3.0))
    assert len(crossers) > 0
    start, end = states[0].agents.d[crossers], states[-1].agents.d[crossers]
    assert np.any(np.sign(start) != np.sign(end))  # somebody got to the other side
