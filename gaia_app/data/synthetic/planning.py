"""Scene planning: the route, the ego's start and behaviour, lights and traffic of one clip.

The route begins with a set-up piece chosen for the ego behaviour (a junction to turn at, a red
light to brake for, a green light to pull away from, a curve to cruise through), followed by
random pieces typical of the environment. The heading is kept within ±90° of the start so the
route never loops back onto itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gaia_app.data.synthetic.policy import EgoDriver, EgoPlan
from gaia_app.data.synthetic.road import (
    CORNER_MARGIN,
    Curve,
    Junction,
    LaneGeometry,
    Path,
    RoadLayout,
    Segment,
    Straight,
    build_layout,
)
from gaia_app.data.synthetic.scenario import EGO_START, TRAFFIC_MIX, Scenario, Setting
from gaia_app.data.synthetic.traffic import (
    AgentSpec,
    make_agents,
    place_specs,
    spawn_cross_traffic,
    spawn_lane_traffic,
    spawn_parked,
    spawn_pedestrians,
)
from gaia_app.data.synthetic.world import Agents, CrossRoad, Ego, LightCycle, World

BEHAVIOUR_P = {"cruise": 0.24, "follow": 0.2, "accelerate": 0.12, "brake": 0.14, "turn": 0.16, "lane_change": 0.14}
LEAD_CATEGORIES = ("car", "car", "car", "bus", "truck")
SIDEWALK_WIDTH = 3.0
KERB_WIDTH = 0.25


@dataclass
class ScenePlan:
    """A fully determined clip before simulation."""

    setting: Setting
    world: World
    ego: Ego
    ego_plan: EgoPlan
    roadside: bool
    appearance_seed: int

    @property
    def layout(self) -> RoadLayout:
        return self.world.layout



def sidewalk_offset(geo: LaneGeometry) -> float:
    """|d| of the sidewalk centre line (m)."""
    return geo.edge + geo.shoulder + KERB_WIDTH + SIDEWALK_WIDTH / 2


def choose_behaviour(rng: np.random.Generator, setting: Setting, scenario: Scenario) -> str:
    """The scenario's behaviour, else a random one the road allows (turns need junctions, lane
    changes two lanes)."""
    if scenario.behaviour is not None:
        return scenario.behaviour
    allowed = {b: p for b, p in BEHAVIOUR_P.items()
               if not (b == "turn" and setting.environment in ("highway", "rural"))
               and not (b == "lane_change" and setting.geometry.lanes < 2)}
    names = list(allowed)
    p = np.array(list(allowed.values()))
    return names[int(rng.choice(len(names), p=p / p.sum()))]


def _junction_half(setting: Setting) -> float:
    geo = setting.geometry
    return geo.edge + geo.shoulder + CORNER_MARGIN


def _setup_pieces(rng: np.random.Generator, setting: Setting, behaviour: str, v0: float,
                  duration: float) -> tuple[list[Segment], tuple[str, float] | None]:
    """Route pieces from s=0 through the behaviour's set-up, and the (state, elapsed s) that the
    first junction light must show at t=0 (None: any)."""
    front = EGO_START + Ego.front
    if behaviour == "turn":
        # Start up to half-way through the turn, or early enough to reach it within the clip.
        arc = np.pi / 2 * _junction_half(setting)
        ahead = rng.uniform(-0.5 * arc, 0.6 * v0 * duration + 1.0)
        spec = Junction(kind=str(rng.choice(["four_way", "t_junction"])), turn=str(rng.choice(["left", "right"])),
                        traffic_light=bool(rng.random() < 0.6))
        return [Straight(EGO_START + ahead), spec], ("green", rng.uniform(0.0, 3.0))
    if behaviour == "brake" and setting.environment != "highway" and rng.random() < 0.6:
        stop_at = v0 * v0 / (2 * rng.uniform(1.5, 3.5)) + rng.uniform(3.0, 8.0)
        spec = Junction(kind="four_way", traffic_light=True, crossing=bool(rng.random() < 0.4))
        setback = 6.0 if spec.crossing else 1.0
        return [Straight(front + stop_at + setback), spec], ("red", rng.uniform(0.0, 2.0))
    if behaviour == "accelerate":
        if setting.environment != "highway" and rng.random() < 0.6:  # pull away from a light that turned green
            spec = Junction(kind="four_way", traffic_light=True)
            return [Straight(front + rng.uniform(1.0, 6.0) + 1.0), spec], ("green", rng.uniform(0.0, 1.0))
        return [Straight(EGO_START + rng.uniform(20.0, 120.0))], ("green", rng.uniform(0.0, 2.0))
    if setting.environment != "urban" and rng.random() < 0.35:
        k = rng.choice([-1, 1]) * rng.uniform(1 / 600, 1 / 120) * (0.3 if setting.environment == "highway" else 1.0)
        return [Straight(EGO_START - rng.uniform(0.0, 40.0)), Curve(rng.uniform(80.0, 200.0), float(k))], None
    return [Straight(EGO_START + rng.uniform(20.0, 120.0))], None


def _turn_of(piece: Segment) -> float:
    if isinstance(piece, Curve):
        return piece.length * piece.curvature
    if isinstance(piece, Junction):
        return {"straight": 0.0, "left": np.pi / 2, "right": -np.pi / 2}[piece.turn]
    return 0.0


def _random_piece(rng: np.random.Generator, env: str, heading: float) -> list[Segment]:
    u = rng.random()
    toward_start = -np.sign(heading) if abs(heading) > 0.3 and rng.random() < 0.7 else rng.choice([-1, 1])
    if env == "highway":
        if u < 0.55:
            return [Straight(rng.uniform(200.0, 500.0))]
        return [Curve(rng.uniform(150.0, 400.0), float(toward_start * rng.uniform(1 / 1500, 1 / 500)))]
    if env == "rural":
        if u < 0.1:
            return [Junction(kind=str(rng.choice(["four_way", "t_junction"])), traffic_light=False), Straight(60.0)]
        if u < 0.55:
            return [Straight(rng.uniform(80.0, 250.0))]
        k = rng.uniform(1 / 350, 1 / 80)
        return [Curve(min(rng.uniform(60.0, 200.0), 1.0 / k), float(toward_start * k))]
    p_junction = 0.45 if env == "urban" else 0.3
    if u < p_junction:
        turn = str(rng.choice(["straight", "straight", "left", "right"]))
        if abs(heading + {"straight": 0.0, "left": np.pi / 2, "right": -np.pi / 2}[turn]) > np.pi / 2 + 0.01:
            turn = "straight"
        spec = Junction(kind="four_way" if rng.random() < 0.7 else "t_junction", turn=turn,
                        traffic_light=bool(rng.random() < (0.85 if env == "urban" else 0.5)),
                        crossing=bool(rng.random() < 0.5))
        return [spec, Straight(rng.uniform(40.0, 120.0))]
    if u < p_junction + 0.12:
        k = rng.uniform(1 / 200, 1 / 50)
        return [Curve(min(rng.uniform(30.0, 100.0), 0.8 / k), float(toward_start * k))]
    return [Straight(rng.uniform(50.0, 160.0), crossing=bool(rng.random() < 0.3))]


def random_road(rng: np.random.Generator, setting: Setting, setup: list[Segment], length: float) -> list[Segment]:
    """`setup` followed by random environment pieces until the route is `length` m long."""
    pieces = list(setup)
    heading = sum(_turn_of(p) for p in pieces)
    total = sum(getattr(p, "length", 2 * _junction_half(setting)) for p in pieces)
    if isinstance(pieces[-1], Junction):
        pieces.append(Straight(rng.uniform(40.0, 120.0)))
        total += pieces[-1].length
    while total < length:
        for piece in _random_piece(rng, setting.environment, heading):
            pieces.append(piece)
            heading += _turn_of(piece)
            total += getattr(piece, "length", 2 * _junction_half(setting))
    return pieces


def ego_plan(rng: np.random.Generator, setting: Setting, behaviour: str, scenario: Scenario,
             duration: float) -> tuple[EgoPlan, float]:
    """The ego's plan and its speed at t=0 (m/s)."""
    geo = setting.geometry
    limit = setting.speed_limit / 3.6
    lane = scenario.ego_lane if scenario.ego_lane is not None else int(rng.integers(0, geo.lanes))
    if not 0 <= lane < geo.lanes:
        raise ValueError(f"Scenario.ego_lane: expected 0..{geo.lanes - 1}, got {lane}")
    plan = EgoPlan(behaviour, lane, v_desired=limit * rng.uniform(0.85, 1.05), a_max=rng.uniform(1.2, 2.0))
    v0 = plan.v_desired * rng.uniform(0.8, 1.0)
    if behaviour == "turn":
        v0 = rng.uniform(4.0, 8.0)
    elif behaviour == "accelerate":
        v0, plan.a_max = rng.uniform(0.0, 3.0), rng.uniform(2.0, 3.5)
    elif behaviour == "brake":
        v0 = plan.v_desired * rng.uniform(0.6, 1.0)
        if rng.random() < 0.5:
            plan.brake_t0, plan.brake_decel = rng.uniform(-0.3, 0.6) * duration, rng.uniform(2.5, 6.5)
    elif behaviour == "follow":
        v0 = plan.v_desired * rng.uniform(0.5, 0.95)
    elif behaviour == "lane_change" and geo.lanes >= 2:
        plan.change_to = (lane + 1 if lane == 0 else lane - 1 if lane == geo.lanes - 1
                          else lane + int(rng.choice([-1, 1])))
        plan.change_len = rng.uniform(3.0, 5.0)
        plan.change_t0 = rng.uniform(-0.8 * plan.change_len, max(duration, 0.1))
    if scenario.ego_speed is not None:
        v0 = scenario.ego_speed
    if scenario.ego_actions is not None:
        plan.actions = np.asarray(scenario.ego_actions, dtype=np.float64)
        v0 = float(plan.actions[0, 0])
    return plan, float(v0)


def _lights(rng: np.random.Generator, layout: RoadLayout, first_state: tuple[str, float] | None,
            duration: float) -> list[LightCycle | None]:
    lights: list[LightCycle | None] = []
    for j, site in enumerate(layout.junctions):
        if not site.spec.traffic_light:
            lights.append(None)
            continue
        green = rng.uniform(max(8.0, duration + 4.0), max(20.0, duration + 6.0))
        ahead = site.s_exit > EGO_START
        if first_state is not None and ahead and all(not layout.junctions[i].spec.traffic_light or
                                                      layout.junctions[i].s_exit <= EGO_START for i in range(j)):
            lights.append(LightCycle.starting(green, *first_state))
        else:
            lights.append(LightCycle(green, rng.uniform(0.0, 2 * green + 8.0)))
    return lights


def _cross_roads(layout: RoadLayout) -> list[CrossRoad]:
    roads = []
    for j, site in enumerate(layout.junctions):
        if site.has_cross_traffic:
            heading = site.heading_in + np.pi / 2
            start = site.centre - 150.0 * np.array([np.cos(heading), np.sin(heading)])
            roads.append(CrossRoad(Path.integrate(start, heading, np.zeros(600)), j, 150.0))
    return roads


def _traffic(rng: np.random.Generator, setting: Setting, scenario: Scenario, layout: RoadLayout,
             cross_roads: list[CrossRoad], plan: EgoPlan, v0: float, density: float, duration: float,
             sidewalk_d: float) -> Agents:
    if scenario.agents is not None:
        return place_specs(rng, list(scenario.agents), layout, EGO_START, Ego.front, plan.lane, 0)
    if density <= 0:
        return place_specs(rng, [], layout, EGO_START, Ego.front, plan.lane, 0)
    geo = layout.geometry
    window = (EGO_START - 150.0, EGO_START + 260.0 + 35.0 * duration)
    corridor_end = EGO_START + 2.5 * v0 + 25.0
    corridors = [(EGO_START - 12.0, corridor_end, float(geo.lane_offset(plan.lane)))]
    if plan.change_to is not None:
        corridors.append((EGO_START - 25.0, corridor_end, float(geo.lane_offset(plan.change_to))))
    parts = []
    # the lead of a "follow" clip is part of the scene whoever drives the ego: a re-simulation of the clip under
    # other commands (plan.actions given) keeps it, and keeps every later draw of the traffic the same
    if plan.behaviour == "follow":
        lead = AgentSpec(str(rng.choice(LEAD_CATEGORIES)), gap=rng.uniform(6.0, 35.0),
                         speed=v0 + rng.uniform(-1.5, 1.0))
        parts.append(place_specs(rng, [lead], layout, EGO_START, Ego.front, plan.lane, 0))
        corridors[0] = (corridors[0][0], EGO_START + lead.gap + 8.0, corridors[0][2])
    limit = setting.speed_limit / 3.6
    groups = [spawn_lane_traffic(rng, layout, window, density, limit, TRAFFIC_MIX[setting.environment], corridors),
              spawn_cross_traffic(rng, cross_roads, layout, density)]
    if setting.parking:
        groups.append(spawn_parked(rng, layout, window, occupancy=min(0.9, 0.45 * density)))
    if setting.sidewalk:
        walkers = density * (1.0 if setting.environment == "urban" else 0.4)
        groups.append(spawn_pedestrians(rng, layout, window, walkers, sidewalk_d, duration))
    for group in groups:
        first = sum(len(p) for p in parts)
        parts.append(make_agents(rng, **group, first_id=first))
    return Agents.concat(parts)


def make_plan(rng: np.random.Generator, scenario: Scenario, setting: Setting, clip_len: int, fps: float,
              agent_density: float) -> ScenePlan:
    """Plan one clip: route, lights, traffic and the ego's start, all drawn from `rng`."""
    duration = clip_len / fps
    behaviour = choose_behaviour(rng, setting, scenario)
    plan, v0 = ego_plan(rng, setting, behaviour, scenario, duration)
    if scenario.road is not None:
        segments, first_state = list(scenario.road), None
    else:
        setup, first_state = _setup_pieces(rng, setting, behaviour, v0, duration)
        segments = random_road(rng, setting, setup, EGO_START + 35.0 * duration + 450.0)
    if scenario.traffic_light is not None:
        first_state = (scenario.traffic_light, 0.5)
    sides = rng.choice([-1, 1], size=sum(isinstance(p, Junction) for p in segments))
    layout = build_layout(segments, setting.geometry, sides)
    needed = EGO_START + 60.0 + (float(np.max(plan.actions[:, 0])) * duration if plan.actions is not None else 0.0)
    if layout.path.length < needed:
        raise ValueError(f"Scenario.road: the route is {layout.path.length:.0f} m long; the ego starts at "
                         f"{EGO_START:.0f} m and needs at least {needed:.0f} m")
    cross_roads = _cross_roads(layout)
    agents = _traffic(rng, setting, scenario, layout, cross_roads, plan, v0, agent_density, duration,
                      sidewalk_offset(layout.geometry))
    world = World(layout, cross_roads, _lights(rng, layout, first_state, duration), agents,
                  np.random.default_rng(int(rng.integers(2 ** 63))))
    d0 = EgoDriver(plan, world).target_offset(0.0)
    x, y = layout.path.offset(EGO_START, d0)
    ego = Ego(float(x), float(y), float(layout.path.heading_at(EGO_START)), v0, EGO_START, d0)
    return ScenePlan(setting, world, ego, plan, scenario.roadside, int(rng.integers(2 ** 31)))
