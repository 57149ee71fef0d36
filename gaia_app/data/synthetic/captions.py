"""Text captions from the scene state, one per frame (GAIA-1 §2.2 text conditioning).

Every caption states the time of day and the weather; the other facts (road, ego motion, traffic
light, lead agent, junction, crossing, speed limit) appear when they hold. Wording varies between
clips: each fact has several phrasings and the clip's generator picks one per fact and an order,
kept for the whole clip so captions change only when the scene does. Numbers are rounded: the
lead distance to whole metres, the speed to whole km/h or mph.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from gaia_app.data.synthetic.scenario import COUNTRIES, MPH, Setting
from gaia_app.data.synthetic.simulate import FrameState

PHRASES: dict[str, tuple[str, ...]] = {
    "day": ("It is daytime.", "Driving during the day.", "It is day."),
    "dusk": ("It is dusk.", "Driving at dusk.", "The sun is setting; it is dusk."),
    "night": ("It is night.", "Driving at night.", "It is night-time."),
    "clear": ("The weather is clear.", "Clear weather.", "The sky is clear."),
    "rain": ("It is raining.", "Driving in the rain.", "Rain is falling."),
    "fog": ("It is foggy.", "Driving through fog.", "Visibility is low in the fog."),
    "snow": ("It is snowing.", "Driving in the snow.", "Snow is falling."),
    "urban": ("We drive through a city.", "An urban street.", "We are in the city."),
    "suburban": ("We drive through a suburb.", "A suburban street.", "We are in a residential area."),
    "rural": ("We are on a country road.", "A rural road.", "We drive through the countryside."),
    "highway": ("We are on a highway.", "Highway driving.", "We drive on the motorway."),
    "stopped": ("We are stopped.", "The car is standing still.", "We are waiting."),
    "cruising": ("We drive at {speed}.", "Our speed is {speed}.", "We are travelling at {speed}."),
    "accelerating": ("We accelerate, now at {speed}.", "We speed up to {speed}.", "Accelerating through {speed}."),
    "braking": ("We brake, now at {speed}.", "We slow down to {speed}.", "Braking at {speed}."),
    "turn_left": ("We turn left.", "We are taking a left turn.", "Turning left."),
    "turn_right": ("We turn right.", "We are taking a right turn.", "Turning right."),
    "lane_change": ("We change lanes.", "We are changing lanes.", "Lane change in progress."),
    "light": ("The traffic light is {state}.", "The light ahead is {state}.", "The signal shows {state}."),
    "lead": ("We are {distance} meters behind a {category}.", "A {category} is {distance} meters ahead of us.",
             "We follow a {category} at {distance} meters."),
    "intersection": ("There is an intersection ahead.", "We approach an intersection.", "A junction is coming up."),
    "crossing": ("There is a pedestrian crossing ahead.", "A zebra crossing is ahead.", "We approach a crosswalk."),
    "pedestrians": ("A pedestrian is crossing the road.", "Someone is walking across the road.",
                    "A person crosses in front of us."),
    "limit": ("The speed limit is {limit}.", "Speed limit {limit}.", "The limit here is {limit}."),
    "lanes": ("The road has {lanes} in our direction.", "We have {lanes} our way.", "{lanes} in each direction."),
}
"""Phrasings per fact; placeholders are filled from the frame."""
LANE_WORDS = {1: "one lane", 2: "two lanes", 3: "three lanes", 4: "four lanes"}


class Captioner:
    """Writes the captions of one clip; wording choices come from the clip's generator."""

    def __init__(self, rng: np.random.Generator, setting: Setting):
        self.setting = setting
        self.choice = {key: int(rng.integers(0, len(options))) for key, options in PHRASES.items()}
        self.order = list(rng.permutation(["road", "motion", "light", "lead", "junction", "crossing", "limit",
                                           "lanes"]))
        self.optional = {name: bool(rng.random() < 0.5) for name in ("road", "limit", "lanes")}
        self.mph = COUNTRIES[setting.country].speed_unit == "mph"

    def phrase(self, key: str, **values: Any) -> str:
        text = PHRASES[key][self.choice[key]].format(**values)
        return text[0].upper() + text[1:]

    def speed_text(self, speed: float) -> str:
        kmh = speed * 3.6
        return f"{round(kmh / MPH)} mph" if self.mph else f"{round(kmh)} km/h"

    def caption(self, state: FrameState, meta: dict[str, Any]) -> str:
        """The caption of one frame from its state and frame metadata."""
        setting = self.setting
        parts = [self.phrase(setting.time_of_day), self.phrase(setting.weather)]
        facts = {
            "road": self.phrase(setting.environment) if self.optional["road"] else None,
            "motion": self.phrase(meta["manoeuvre"], speed=self.speed_text(state.speed)),
            "light": self.phrase("light", state=meta["traffic_light"]) if meta["traffic_light"] else None,
            "lead": self._lead(meta["lead_agent"]),
            "junction": (self.phrase("intersection") if meta["intersection"] and meta["intersection_distance"] < 60
                         else None),
            "crossing": self._crossing(meta),
            "limit": self.phrase("limit", limit=f"{setting.speed_sign} {'mph' if self.mph else 'km/h'}")
            if self.optional["limit"] else None,
            "lanes": self.phrase("lanes", lanes=LANE_WORDS[setting.geometry.lanes]) if self.optional["lanes"] else None,
        }
        parts += [facts[name] for name in self.order if facts[name]]
        return " ".join(parts)

    def _lead(self, lead: dict[str, Any] | None) -> str | None:
        if lead is None or lead["distance"] > 60:
            return None
        return self.phrase("lead", distance=int(round(lead["distance"])), category=lead["category"])

    def _crossing(self, meta: dict[str, Any]) -> str | None:
        if meta["pedestrians_crossing"] > 0 and meta["crossing"]:
            return self.phrase("pedestrians")
        if meta["crossing"] and meta["crossing_distance"] < 60:
            return self.phrase("crossing")
        return None
