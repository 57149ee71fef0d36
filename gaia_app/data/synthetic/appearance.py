"""Look of a clip: time of day (sky, sun, ambient light, headlights), weather (haze and fog
visibility, rain, snow) and the surface palette.

Shading model (per face or per ground pixel), colours RGB in 0..1:
    lit = albedo * (ambient + sun_colour * max(0, n·sun) + headlights(point))
    seen = lit * (1 - f) + fog_colour * f,   f = 1 - exp(-distance / visibility)
Emissive parts (lamps, lit windows, vehicle lights) skip the shading and only get fog.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

HEADLIGHT_COLOUR = np.array([1.0, 0.95, 0.85])


@dataclass
class Appearance:
    """Everything colour-related of one clip.

    ambient, sun_colour, fog_colour, sky_top, sky_horizon: (3,) RGB; sun_dir: (3,) unit vector
    towards the sun in the world frame; visibility: metres for fog/haze; headlights: strength of
    the ego's beams (0 = off); lights_on: lamps, windows and vehicle lights glow; palette:
    surface name → (3,) albedo; precipitation: 'none' | 'rain' | 'snow'.
    """

    weather: str
    time_of_day: str
    ambient: np.ndarray
    sun_colour: np.ndarray
    sun_dir: np.ndarray
    fog_colour: np.ndarray
    visibility: float
    sky_top: np.ndarray
    sky_horizon: np.ndarray
    headlights: float
    lights_on: bool
    precipitation: str
    palette: dict[str, np.ndarray] = field(default_factory=dict)
    cloud_cover: float = 0.3
    seed: int = 0

    def shade(self, albedo: np.ndarray, normal: np.ndarray, headlight: np.ndarray | None = None) -> np.ndarray:
        """(n, 3) lit colour of surfaces with (n, 3) albedo and (n, 3) unit normals; headlight:
        (n,) extra light from the ego's beams."""
        light = self.ambient + self.sun_colour * np.maximum(0.0, normal @ self.sun_dir)[:, None]
        if headlight is not None:
            light = light + headlight[:, None] * HEADLIGHT_COLOUR
        return albedo * light

    def fog_factor(self, distance: np.ndarray) -> np.ndarray:
        """Fraction of fog colour at `distance` metres (0 near, → 1 far)."""
        return 1.0 - np.exp(-np.asarray(distance) / self.visibility)

    def fog(self, colour: np.ndarray, distance: np.ndarray) -> np.ndarray:
        """(n, 3) colours seen through haze/fog at (n,) distances."""
        f = self.fog_factor(distance)[:, None]
        return colour * (1 - f) + self.fog_colour * f


def headlight_intensity(points_ego: np.ndarray, strength: float) -> np.ndarray:
    """(n,) light from the ego's low beams at (n, 3) ego-frame points: a forward cone ~40 m long."""
    if strength <= 0:
        return np.zeros(len(points_ego))
    x, y = points_ego[:, 0] - 2.0, points_ego[:, 1]
    spread = 0.3 * np.maximum(x, 0.0) + 0.9
    reach = np.clip(1.0 - x / 45.0, 0.0, 1.0) ** 2
    start = np.clip(x / 4.0, 0.0, 1.0)
    return strength * np.exp(-(y / spread) ** 2) * reach * start


def _sun(rng: np.random.Generator, elevation_deg: float) -> np.ndarray:
    az = rng.uniform(0, 2 * np.pi)
    el = np.radians(elevation_deg)
    return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def _base_palette(rng: np.random.Generator, environment: str) -> dict[str, np.ndarray]:
    def jitter(c, a: float = 0.04) -> np.ndarray:
        return np.clip(np.asarray(c) + rng.uniform(-a, a, 3) + rng.uniform(-a, a), 0, 1)

    grey = rng.uniform(0.24, 0.36)
    grass = [[0.26, 0.42, 0.17], [0.34, 0.44, 0.2], [0.42, 0.44, 0.24], [0.22, 0.36, 0.16]][rng.integers(0, 4)]
    ground = [0.46, 0.44, 0.41] if environment == "urban" else grass
    return {
        "ground": jitter(ground), "grass": jitter(grass), "grass_dark": jitter(np.array(grass) * 0.8),
        "asphalt": jitter([grey, grey, grey * 1.04], 0.02),
        "patch": jitter([grey * 0.8, grey * 0.8, grey * 0.82], 0.02),
        "crack": np.array([grey * 0.55, grey * 0.55, grey * 0.56]),
        "shoulder": jitter([grey * 1.1, grey * 1.1, grey * 1.1], 0.02),
        "sidewalk": jitter([0.58, 0.56, 0.52]), "kerb": jitter([0.7, 0.7, 0.68], 0.03),
        "white": jitter([0.86, 0.86, 0.84], 0.03), "yellow": jitter([0.86, 0.68, 0.16], 0.03),
        "median": jitter(grass), "dirt": jitter([0.42, 0.36, 0.28]),
    }


def _weather_palette(palette: dict[str, np.ndarray], weather: str) -> dict[str, np.ndarray]:
    p = dict(palette)
    if weather == "rain":  # wet surfaces are darker
        for k in ("asphalt", "patch", "crack", "shoulder", "sidewalk", "ground", "grass", "dirt"):
            p[k] = p[k] * 0.72
    if weather == "snow":
        for k in ("grass", "grass_dark", "median", "ground", "dirt"):
            p[k] = np.array([0.86, 0.88, 0.92]) - (0.04 if k == "grass_dark" else 0.0)
        p["sidewalk"] = np.array([0.8, 0.81, 0.84])
        p["asphalt"] = p["asphalt"] * 0.6 + 0.28
        p["patch"] = p["asphalt"] * 0.85
        p["crack"] = p["asphalt"] * 0.7
        p["shoulder"] = np.array([0.82, 0.83, 0.86])
        p["white"] = np.array([0.9, 0.9, 0.92])
    return p


def make_appearance(rng: np.random.Generator, weather: str, time_of_day: str, environment: str) -> Appearance:
    """Draw the look of a clip with the given weather and time of day."""
    overcast = weather in ("rain", "snow", "fog")
    if time_of_day == "day":
        sun_dir, sun = _sun(rng, rng.uniform(25, 65)), np.array([1.0, 0.97, 0.9]) * (0.25 if overcast else 0.6)
        ambient = np.full(3, 0.55 if overcast else 0.5) * np.array([0.97, 0.99, 1.03])
        sky_top, sky_horizon = np.array([0.25, 0.47, 0.8]), np.array([0.7, 0.8, 0.9])
        headlights, lights_on = 0.0, False
    elif time_of_day == "dusk":
        sun_dir, sun = _sun(rng, rng.uniform(1, 6)), np.array([1.0, 0.6, 0.35]) * (0.15 if overcast else 0.45)
        ambient = np.array([0.36, 0.3, 0.3])
        sky_top, sky_horizon = np.array([0.16, 0.18, 0.38]), np.array([0.95, 0.55, 0.32])
        headlights, lights_on = 0.5, True
    else:
        sun_dir, sun = np.array([0.0, 0.0, 1.0]), np.zeros(3)
        ambient = np.array([0.05, 0.06, 0.09]) * rng.uniform(0.8, 1.3)
        sky_top, sky_horizon = np.array([0.01, 0.015, 0.04]), np.array([0.07, 0.07, 0.1])
        if environment == "urban":
            sky_horizon = np.array([0.11, 0.085, 0.075])  # light pollution
        headlights, lights_on = 1.3, True
    visibility = {"clear": rng.uniform(900, 1600), "rain": rng.uniform(250, 450), "snow": rng.uniform(120, 250),
                  "fog": rng.uniform(30, 70)}[weather]
    if overcast:
        grey = np.array([0.62, 0.64, 0.67]) if weather != "snow" else np.array([0.78, 0.79, 0.82])
        tint = {"day": 1.0, "dusk": 0.55, "night": 0.09}[time_of_day]
        sky_top = grey * tint * 0.85 + (sky_top * 0.2 if time_of_day == "dusk" else 0.0)
        sky_horizon = grey * tint + (sky_horizon * 0.15 if time_of_day == "dusk" else 0.0)
    fog_colour = sky_horizon * (1.0 if weather != "fog" else 0.95) if time_of_day != "night" else sky_horizon * 1.5
    palette = _weather_palette(_base_palette(rng, environment), weather)
    return Appearance(weather, time_of_day, ambient, sun, sun_dir, fog_colour, visibility, sky_top, sky_horizon,
                      headlights, lights_on, {"rain": "rain", "snow": "snow"}.get(weather, "none"), palette,
                      cloud_cover=rng.uniform(0.0, 0.6) if not overcast else 0.0, seed=int(rng.integers(2 ** 31)))
