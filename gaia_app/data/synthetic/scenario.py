"""Clip-level choices: the explicit `Scenario` (for tests and controlled experiments) and the
drawn `Setting` (environment, country, weather, time of day, speed limit, road cross-section).

A `Scenario` field left at None is drawn from the clip's seeded generator; a field that is set
is used as is. `planning.make_plan` turns both into a full scene.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from gaia_app.data.synthetic.policy import BEHAVIOURS
from gaia_app.data.synthetic.road import LaneGeometry, Segment
from gaia_app.data.synthetic.traffic import AgentSpec
from gaia_app.data.synthetic.world import BUS, CAR, CYCLIST, TRUCK

ENVIRONMENTS = {"urban": 0.35, "suburban": 0.25, "rural": 0.2, "highway": 0.2}
WEATHERS = ("clear", "rain", "fog", "snow")
TIMES_OF_DAY = ("day", "dusk", "night")
EGO_START = 100.0
"""Route s (m) of the ego's rear axle at t=0: there is road behind it for the rear cameras."""
MPH = 1.609344


@dataclass(frozen=True)
class Country:
    """Traffic conventions: drive_sign -1 keeps right, +1 keeps left; speed unit; centre-line colour."""

    drive_sign: int
    speed_unit: str
    centre_colour: str


COUNTRIES = {
    "DE": Country(-1, "km/h", "white"), "FR": Country(-1, "km/h", "white"), "NL": Country(-1, "km/h", "white"),
    "US": Country(-1, "mph", "yellow"), "GB": Country(1, "mph", "white"), "JP": Country(1, "km/h", "white"),
}
SPEED_LIMITS = {  # environment: (km/h signs, mph signs)
    "urban": ((30, 50), (20, 25, 30)),
    "suburban": ((30, 50, 60), (25, 30, 35, 40)),
    "rural": ((70, 80, 100), (45, 50, 55, 60)),
    "highway": ((100, 120, 130), (55, 65, 70)),
}
TRAFFIC_MIX = {
    "urban": {CAR: 0.7, BUS: 0.1, TRUCK: 0.08, CYCLIST: 0.12},
    "suburban": {CAR: 0.75, BUS: 0.06, TRUCK: 0.09, CYCLIST: 0.1},
    "rural": {CAR: 0.72, BUS: 0.05, TRUCK: 0.18, CYCLIST: 0.05},
    "highway": {CAR: 0.68, BUS: 0.07, TRUCK: 0.25},
}


@dataclass(frozen=True)
class Scenario:
    """Explicit choices for a clip; None means "draw it from the seed".

    environment: 'urban' | 'suburban' | 'rural' | 'highway'; country: key of COUNTRIES;
    weather: one of WEATHERS; time_of_day: one of TIMES_OF_DAY; road: route segments, the ego
    starting EGO_START m along them; lanes: per direction (1–4); behaviour: one of BEHAVIOURS;
    ego_lane: 0 = kerb-side lane; ego_speed: m/s at t=0; ego_actions: (clip_len, 2) open-loop
    (speed m/s, curvature 1/m) replacing the policy; agents: explicit agents (an empty tuple gives
    an empty road); roadside: buildings, trees, lamps and signs; traffic_light: state of the
    first light ahead at t=0.
    """

    environment: str | None = None
    country: str | None = None
    weather: str | None = None
    time_of_day: str | None = None
    road: tuple[Segment, ...] | None = None
    lanes: int | None = None
    behaviour: str | None = None
    ego_lane: int | None = None
    ego_speed: float | None = None
    ego_actions: np.ndarray | None = field(default=None, compare=False)
    agents: tuple[AgentSpec, ...] | None = None
    roadside: bool = True
    traffic_light: str | None = None

    def __post_init__(self) -> None:
        _check_choice("environment", self.environment, tuple(ENVIRONMENTS))
        _check_choice("country", self.country, tuple(COUNTRIES))
        _check_choice("weather", self.weather, WEATHERS)
        _check_choice("time_of_day", self.time_of_day, TIMES_OF_DAY)
        _check_choice("behaviour", self.behaviour, BEHAVIOURS)
        _check_choice("traffic_light", self.traffic_light, ("red", "amber", "green"))
        if self.lanes is not None and not 1 <= self.lanes <= 4:
            raise ValueError(f"Scenario.lanes: expected 1..4 lanes per direction, got {self.lanes}")


def _check_choice(name: str, value: str | None, allowed: tuple[str, ...]) -> None:
    if value is not None and value not in allowed:
        raise ValueError(f"Scenario.{name}: expected one of {allowed}, got {value!r}")


@dataclass
class Setting:
    """Clip-level categories and the road cross-section."""

    environment: str
    country: str
    weather: str
    time_of_day: str
    speed_limit: float
    """km/h (signs in mph countries are converted)."""
    speed_sign: int
    """The number on the sign, in the country's unit."""
    geometry: LaneGeometry
    lane_types: list[str]
    sidewalk: bool
    parking: bool


def draw_category(rng: np.random.Generator, mix: Mapping[str, float], name: str) -> str:
    """One key of `mix` drawn with its (unnormalised) probability."""
    keys = list(mix)
    p = np.array([float(mix[k]) for k in keys])
    if np.any(p < 0) or p.sum() <= 0:
        raise ValueError(f"{name}: expected non-negative probabilities with a positive sum, got {dict(mix)}")
    return keys[int(rng.choice(len(keys), p=p / p.sum()))]


def draw_setting(rng: np.random.Generator, scenario: Scenario, weather_mix: Mapping[str, float],
                 time_of_day_mix: Mapping[str, float]) -> Setting:
    env = scenario.environment or draw_category(rng, ENVIRONMENTS, "environment")
    country_name = scenario.country or str(rng.choice(sorted(COUNTRIES)))
    country = COUNTRIES[country_name]
    weather = scenario.weather or draw_category(rng, weather_mix, "weather_mix")
    tod = scenario.time_of_day or draw_category(rng, time_of_day_mix, "time_of_day_mix")
    lane_range = {"urban": (1, 3), "suburban": (1, 2), "rural": (1, 1), "highway": (2, 4)}[env]
    lanes = scenario.lanes or int(rng.integers(lane_range[0], lane_range[1] + 1))
    parking = env in ("urban", "suburban") and rng.random() < 0.6
    shoulder = {"urban": 2.2 if parking else 0.3, "suburban": 2.2 if parking else 0.5,
                "rural": rng.uniform(0.4, 1.0), "highway": rng.uniform(2.0, 3.0)}[env]
    geometry = LaneGeometry(lanes=lanes,
                            lane_width=rng.uniform(3.0, 3.5) if env != "highway" else rng.uniform(3.5, 3.75),
                            median=rng.uniform(3.0, 8.0) if env == "highway" else 0.0, shoulder=shoulder,
                            drive_sign=country.drive_sign)
    signs = SPEED_LIMITS[env][1 if country.speed_unit == "mph" else 0]
    sign = int(rng.choice(signs))
    limit = round(sign * MPH, 1) if country.speed_unit == "mph" else float(sign)
    return Setting(env, country_name, weather, tod, limit, sign, geometry, _lane_types(rng, env, lanes, country),
                   sidewalk=env in ("urban", "suburban"), parking=parking)


def _lane_types(rng: np.random.Generator, env: str, lanes: int, country: Country) -> list[str]:
    """Marking of each own-side lane boundary, from the centre line to the kerb."""
    if env == "highway":
        centre = "solid"
    elif lanes >= 2 or country.centre_colour == "yellow":
        centre = "double_solid"
    else:
        centre = "dashed" if rng.random() < 0.6 else "solid"
    kerb = "none" if env == "urban" or (env == "suburban" and rng.random() < 0.5) else "solid"
    return [centre] + ["dashed"] * (lanes - 1) + [kerb]
