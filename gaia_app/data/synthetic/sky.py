"""Things at infinity: distant skylines (hills, tree lines, city blocks), clouds, sun glow and
stars. They are fixed in world azimuth, so they slide across the image as the ego turns."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from gaia_app.data.synthetic.appearance import Appearance
from gaia_app.data.synthetic.render import SHIFT, CameraRenderer

PROFILE_BINS = 720
"""Skyline elevation samples over 360° of azimuth."""


@dataclass
class Sky:
    """skylines: (elevation (PROFILE_BINS,) degrees, colour (3,) 0..1), far to near;
    puffs: (n, 4) cloud ellipses az, el, half-width, half-height (degrees) with puff_colour (n, 3);
    stars: (m, 3) az, el (degrees), brightness; sun: (3,) world direction or None; glow_colour,
    glow_radius (degrees)."""

    skylines: list[tuple[np.ndarray, np.ndarray]]
    puffs: np.ndarray
    puff_colour: np.ndarray
    stars: np.ndarray
    sun: np.ndarray | None
    glow_colour: np.ndarray
    glow_radius: float


def _hills(rng: np.random.Generator, base: float, amplitude: float, waves: int) -> np.ndarray:
    az = np.linspace(0, 2 * np.pi, PROFILE_BINS, endpoint=False)
    k = rng.integers(1, waves + 1, 6)
    profile = base + sum(amplitude * rng.uniform(0.3, 1.0) * np.sin(ki * az + rng.uniform(0, 2 * np.pi))
                         for ki in k) / 3
    return np.maximum(profile, 0.15)


def _tree_line(rng: np.random.Generator) -> np.ndarray:
    rough = np.convolve(rng.normal(0, 1, PROFILE_BINS + 8), np.ones(4) / 4, mode="valid")[:PROFILE_BINS]
    return np.maximum(0.9 + 0.35 * rough + _hills(rng, 0.0, 0.8, 5), 0.2)


def _city(rng: np.random.Generator) -> np.ndarray:
    profile = np.full(PROFILE_BINS, 0.4)
    i = 0
    while i < PROFILE_BINS:
        width = int(rng.integers(3, 14))
        profile[i:i + width] = rng.uniform(0.6, 2.5) if rng.random() < 0.8 else 0.4
        i += width
    return profile


def make_sky(rng: np.random.Generator, appearance: Appearance, environment: str) -> Sky:
    """The sky of one clip for its appearance and environment."""
    haze = appearance.sky_horizon

    def mix(colour, amount: float) -> np.ndarray:
        return np.asarray(colour) * (1 - amount) + haze * amount

    visible = 0.0 if appearance.visibility < 100 else 1.0  # fog hides every skyline
    dark = 0.25 if appearance.time_of_day == "night" else 1.0
    skylines = [(_hills(rng, 1.2, 2.5, 4), mix(np.array([0.35, 0.42, 0.45]) * dark, 0.55))]
    if environment == "urban":
        skylines.append((_city(rng), mix(np.array([0.42, 0.44, 0.5]) * dark, 0.45)))
    else:
        skylines.append((_tree_line(rng), mix(np.array([0.13, 0.22, 0.12]) * dark, 0.35)))
    if visible == 0.0:
        skylines = []
    n_clouds = int(round(appearance.cloud_cover * 14)) if appearance.time_of_day != "night" else 0
    puffs, colours = [], []
    tint = np.array([1.0, 0.72, 0.6]) if appearance.time_of_day == "dusk" else np.ones(3)
    for _ in range(n_clouds):
        az, el = rng.uniform(0, 360), rng.uniform(5, 25)
        w, h = rng.uniform(3, 10), rng.uniform(0.8, 2.5)
        shade = rng.uniform(0.85, 1.0)
        for _ in range(int(rng.integers(3, 6))):
            puffs.append([az + rng.uniform(-w, w) * 0.7, el + rng.uniform(-h, h) * 0.4, w * rng.uniform(0.4, 0.7),
                          h * rng.uniform(0.6, 1.0)])
            brightness = shade * rng.uniform(0.9, 1.0) * (0.95 if appearance.time_of_day == "day" else 0.7)
            colours.append(np.clip(tint * brightness, 0, 1))
    clear_night = (appearance.time_of_day == "night" and appearance.precipitation == "none"
                   and appearance.visibility > 100)
    stars = np.c_[rng.uniform(0, 360, 90), rng.uniform(4, 70, 90), rng.uniform(0.3, 0.9, 90)]
    stars = stars if clear_night else np.zeros((0, 3))
    overcast = appearance.weather != "clear"
    sun = None if overcast or appearance.time_of_day == "night" else appearance.sun_dir
    glow = np.array([1.0, 0.98, 0.9]) if appearance.time_of_day == "day" else np.array([1.0, 0.7, 0.35])
    return Sky(skylines, np.array(puffs).reshape(-1, 4), np.array(colours).reshape(-1, 3), stars, sun, glow,
               6.0 if appearance.time_of_day == "day" else 14.0)


def _directions(az_deg: np.ndarray, el_deg: np.ndarray) -> np.ndarray:
    az, el = np.radians(az_deg), np.radians(el_deg)
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)


def draw_sky(img: np.ndarray, renderer: CameraRenderer, sky: Sky, cam_from_world: np.ndarray) -> None:
    """Draw skylines, clouds, stars and sun glow for one camera (in place)."""
    rot = cam_from_world[:3, :3]
    forward = rot.T @ np.array([0.0, 0.0, 1.0])
    heading = np.degrees(np.arctan2(forward[1], forward[0]))
    half = np.degrees(np.arctan(renderer.w / 2 / renderer.fx)) + 8.0
    az = heading + np.linspace(-half, half, 48)
    for profile, colour in sky.skylines:
        el = np.interp(az % 360.0, np.linspace(0, 360, PROFILE_BINS, endpoint=False), profile, period=360.0)
        top = _directions(az, el)
        bottom = _directions(az[[-1, 0]], np.full(2, -0.3))
        pts = renderer.project(np.concatenate([top, bottom]) @ rot.T * 1e4)
        cv2.fillPoly(img, [pts], (np.clip(colour, 0, 1) * 255).tolist(), cv2.LINE_AA, SHIFT)
    _draw_puffs(img, renderer, sky, rot, heading, half)
    for a, e, b in sky.stars:
        cam = rot @ _directions(np.array(a), np.array(e))
        if cam[2] > 0.1:
            cv2.circle(img, tuple(renderer.project(cam).tolist()), 1 << (SHIFT - 1), (255 * b,) * 3, -1, cv2.LINE_AA,
                       SHIFT)
    if sky.sun is not None:
        _draw_glow(img, renderer, sky, rot @ sky.sun)


def _draw_puffs(img, renderer: CameraRenderer, sky: Sky, rot: np.ndarray, heading: float, half: float) -> None:
    if len(sky.puffs) == 0:
        return
    delta = (sky.puffs[:, 0] - heading + 180.0) % 360.0 - 180.0
    for (a, e, w, h), colour in zip(sky.puffs[np.abs(delta) < half + 20], sky.puff_colour[np.abs(delta) < half + 20]):
        cam = rot @ _directions(np.array(a), np.array(e))
        if cam[2] <= 0.1:
            continue
        centre = tuple(renderer.project(cam).tolist())
        axes = (int(np.radians(w) * renderer.fx * (1 << SHIFT)), int(np.radians(h) * renderer.fy * (1 << SHIFT)))
        cv2.ellipse(img, centre, axes, 0, 0, 360, (np.clip(colour, 0, 1) * 255).tolist(), -1, cv2.LINE_AA, SHIFT)


def _draw_glow(img: np.ndarray, renderer: CameraRenderer, sky: Sky, sun_cam: np.ndarray) -> None:
    """Soft additive glow around the sun, computed on the region it covers only."""
    if sun_cam[2] <= 0.05:
        return
    u = renderer.fx * sun_cam[0] / sun_cam[2] + renderer.cx
    v = renderer.fy * sun_cam[1] / sun_cam[2] + renderer.cy
    radius = np.radians(sky.glow_radius) * renderer.fx
    x0, x1 = int(max(0, u - 2 * radius)), int(min(renderer.w, u + 2 * radius + 1))
    y0, y1 = int(max(0, v - 2 * radius)), int(min(renderer.horizon_row + 2, renderer.h, v + 2 * radius + 1))
    if x0 >= x1 or y0 >= y1:
        return
    jj, ii = np.meshgrid(np.arange(x0, x1) + 0.5, np.arange(y0, y1) + 0.5)
    r2 = ((jj - u) ** 2 + (ii - v) ** 2) / max(radius, 1e-3) ** 2
    sky_only = renderer.rays_ego[y0:y1, x0:x1, 2] > 0
    alpha = (0.75 * np.exp(-r2) + 0.25 * (r2 < 0.02)) * sky_only
    roi = img[y0:y1, x0:x1].astype(np.float32)
    roi += alpha[..., None] * (sky.glow_colour * 255.0 - roi)
    img[y0:y1, x0:x1] = np.clip(roi, 0, 255).astype(np.uint8)
