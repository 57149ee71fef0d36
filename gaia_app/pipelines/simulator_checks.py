"""What the closed-loop simulator accepts (pipelines/simulator.py, pipelines/vector_simulator.py), checked where it
enters: each refusal is one line naming the argument or option, the value and what was expected.

Legend: N sub-episodes of a vector env.

An action is two real numbers (speed m/s, curvature 1/m) inside `COMMAND_RANGES`; text and booleans are refused
rather than converted (numpy would read "10" as text and True as 1.0). A seed is an integer in [0, 2^63), so every
generator it seeds (torch's, numpy's) takes it as it is. Reset options form `EpisodeOptions`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from numbers import Integral, Real
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces

from gaia_app.diffusion.guidance import ClassifierFreeGuidance
from gaia_app.pipelines.gaia1_inputs import COMMAND_RANGES

CONTEXTS = ("synthetic", "folder", "none")
OPTIONS = ("context", "index", "world_seed", "folder", "prompt", "guidance")
SEED_LIMIT = 2**63  # seeds lie in [0, 2^63): an int64 for torch and numpy alike
ACTION_TEXT = "two numbers (speed m/s, curvature 1/m)"


def action_space() -> spaces.Box:
    """(speed m/s, curvature 1/m) float32 within the range a command may take (gaia1_inputs.COMMAND_RANGES)."""
    (speed_low, speed_high), (curv_low, curv_high) = COMMAND_RANGES["speed"], COMMAND_RANGES["curvature"]
    return spaces.Box(np.array([speed_low, curv_low], np.float32), np.array([speed_high, curv_high], np.float32),
                      dtype=np.float32)


def leaves(value: Any) -> list[Any]:
    """The scalars of nested lists and tuples (an array or tensor counts as one leaf: its dtype speaks for it)."""
    if isinstance(value, (list, tuple)):
        return [leaf for item in value for leaf in leaves(item)]
    return [value]


def checked_action(action: Any, space: spaces.Box, name: str = "action") -> np.ndarray:
    """The action as float32 `space.shape` ((2,), or (N, 2) for a vector env); TypeError for text, booleans or
    other non-numbers, ValueError for a wrong shape, a non-finite value or one outside the ranges."""
    if any(isinstance(leaf, (str, bytes, bool, np.bool_)) or leaf is None for leaf in leaves(action)):
        raise TypeError(f"{name}={action!r}: expected {ACTION_TEXT}, not text, booleans or None")
    try:
        raw = np.asarray(action)
    except (TypeError, ValueError):
        raise TypeError(f"{name}={action!r}: expected {ACTION_TEXT}") from None
    if raw.dtype.kind not in "fiu":  # bool, text, object or complex arrays and tensors
        raise TypeError(f"{name}={action!r}: expected {ACTION_TEXT}, got an array of dtype {raw.dtype}")
    value = raw.astype(np.float32)
    if value.shape != space.shape:
        raise ValueError(f"{name} of shape {value.shape}: expected {space.shape} ({ACTION_TEXT})")
    if not np.all(np.isfinite(value)):
        raise ValueError(f"{name}={value.tolist()}: speed and curvature must be finite numbers")
    if not space.contains(value):
        low, high = space.low.reshape(-1, 2)[0], space.high.reshape(-1, 2)[0]
        raise ValueError(f"{name}={value.tolist()}: speed must lie in [{low[0]:g}, {high[0]:g}] m/s and "
                         f"curvature in [{low[1]:g}, {high[1]:g}] 1/m")
    return value


def checked_integer(value: Any, name: str, low: int = 0, high: int = SEED_LIMIT) -> int:
    """An integer in [low, high) (Python or numpy; booleans and floats such as 1.7 or 2.0 are refused)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, Integral):
        raise TypeError(f"{name}={value!r}: expected an integer in [{low}, {high})")
    if not low <= int(value) < high:
        raise ValueError(f"{name}={value!r}: expected an integer in [{low}, {high})")
    return int(value)


def checked_seed(seed: Any, name: str = "seed") -> int | None:
    """reset's seed: None or an integer in [0, 2^63)."""
    return None if seed is None else checked_integer(seed, name, 0, SEED_LIMIT)


def episode_guidance(value: Any) -> ClassifierFreeGuidance | None | str:
    """reset option "guidance": "pipeline" (the pipeline's own), a scale ≥ 0 (GAIA-1 §5.1 eq. 3, constant over
    tokens; 0 or None: unguided) or a ClassifierFreeGuidance."""
    if value == "pipeline" or value is None or isinstance(value, ClassifierFreeGuidance):
        return value
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, Real):
        raise ValueError(f"reset option guidance={value!r}: expected a scale ≥ 0, None or 'pipeline'")
    scale = float(value)
    if not np.isfinite(scale) or scale < 0:
        raise ValueError(f"reset option guidance={value!r}: expected a finite scale ≥ 0")
    return ClassifierFreeGuidance(scale) if scale > 0 else None


@dataclass(frozen=True)
class EpisodeOptions:
    """reset's options, checked. indices: one clip index per sub-episode (one for a single env)."""

    context: str = "synthetic"
    indices: tuple[int, ...] = (0,)
    world_seed: int = 1000
    folder: Path | None = None
    prompt: str | None = None
    guidance: ClassifierFreeGuidance | None | str = "pipeline"


def checked_indices(value: Any, episodes: int) -> tuple[int, ...]:
    """Option "index": one integer ≥ 0 for every sub-episode, or (vector env) a sequence of `episodes` of them."""
    if isinstance(value, Sequence) and not isinstance(value, (str, bytes)) and episodes > 1:
        if len(value) != episodes:
            raise ValueError(f"reset option index={value!r}: expected one integer or {episodes}, one per sub-episode")
        return tuple(checked_integer(v, "reset option index") for v in value)
    return (checked_integer(value, "reset option index"),) * episodes


def checked_prompt(value: Any) -> str | None:
    """Option "prompt": None or a non-empty caption."""
    if value is not None and (not isinstance(value, str) or not value.strip()):
        raise TypeError(f"reset option prompt={value!r}: expected a non-empty caption (str) or None")
    return value


def checked_options(options: Any, episodes: int = 1) -> EpisodeOptions:
    """reset's `options` (None or a dict with keys among OPTIONS) → EpisodeOptions for `episodes` sub-episodes."""
    if options is None:
        options = {}
    if not isinstance(options, Mapping):
        raise TypeError(f"reset options={options!r}: expected a dict with keys among {OPTIONS}, or None")
    unknown = set(options) - set(OPTIONS)
    if unknown:
        raise ValueError(f"reset options {sorted(map(str, unknown))}: expected keys among {OPTIONS}")
    context = options.get("context", "synthetic")
    if context not in CONTEXTS:
        raise ValueError(f"reset option context={context!r}: expected one of {CONTEXTS}")
    folder = options.get("folder")
    if context == "folder" and not isinstance(folder, (str, Path)):
        raise TypeError(f"reset option folder={folder!r}: context='folder' needs a clip folder path (str)")
    prompt = checked_prompt(options.get("prompt"))
    if context == "none" and prompt is None:
        raise ValueError("reset option context='none' generates the first frame from a prompt: give prompt")
    return EpisodeOptions(context, checked_indices(options.get("index", 0), episodes),
                          checked_integer(options.get("world_seed", 1000), "reset option world_seed"),
                          None if folder is None else Path(folder), prompt,
                          episode_guidance(options.get("guidance", "pipeline")))
