"""Every setting checked where it enters: one table of rules per entry point (generate.py, train.py).

A bad value must fail at once with one line naming the setting, the value and the accepted range, never as an
allocation crash minutes later (`num_futures=100000`), a silent clamp (`decoder_steps=0` quietly meaning the
default), a quietly skipped feature (`guidance.scale=nan` running unguided) or a run that exits 0 having done
nothing (`max_clips=0`). Hydra parses `prompt=123` to an int and `seed=-1` to a negative number; the rules below
turn each into a `SettingError`. Settings that only some modes read are checked whenever they are set: a value
out of range is wrong whichever mode reads it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from omegaconf import DictConfig, OmegaConf

MAX_SEED = 2**32 - 1  # numpy's and Lightning's seed range
MAX_PROMPT_CHARS = 2000


class SettingError(ValueError):
    """A setting outside its accepted range."""


def integer(low: int, high: int | None = None) -> Callable[[Any], str | None]:
    """An int (not a bool) in [low, high]."""
    def check(value: Any) -> str | None:
        if isinstance(value, bool) or not isinstance(value, int) or value < low or (high is not None and value > high):
            return f"an integer in [{low}, {'∞' if high is None else high}]"
        return None
    return check


def number(low: float, high: float = math.inf, low_open: bool = False) -> Callable[[Any], str | None]:
    """A finite real in [low, high] (or (low, high] when low_open)."""
    def check(value: Any) -> str | None:
        valid = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) \
            and (value > low if low_open else value >= low) and value <= high
        return None if valid else f"a finite number in {'(' if low_open else '['}{low:g}, {high:g}]"
    return check


def text(max_chars: int = MAX_PROMPT_CHARS) -> Callable[[Any], str | None]:
    """A string of at most max_chars characters."""
    def check(value: Any) -> str | None:
        return None if isinstance(value, str) and len(value) <= max_chars else \
            f"a text of at most {max_chars} characters (quote numbers: prompt='\"123\"')"
    return check


def one_of(*choices: Any) -> Callable[[Any], str | None]:
    def check(value: Any) -> str | None:
        return None if value in choices else f"one of {list(choices)}"
    return check


@dataclass(frozen=True)
class Rule:
    """`key` (a dotted path; absent keys are skipped) must pass `check`; None passes when `optional`."""

    key: str
    check: Callable[[Any], str | None]
    optional: bool = False


GENERATE_RULES = (
    Rule("seed", integer(0, MAX_SEED)),
    Rule("num_futures", integer(1, 64)),
    Rule("seconds", number(0, 120, low_open=True)),
    Rule("num_clips", integer(1)),
    Rule("max_clips", integer(1), optional=True),
    Rule("fps", number(0, 1000, low_open=True), optional=True),
    Rule("rate", number(0, 100, low_open=True)),
    Rule("upsample", integer(0, 4)),
    Rule("batch_size", integer(1)),
    Rule("workers", integer(0, 256)),
    Rule("decoder_steps", integer(1, 1000), optional=True),
    Rule("prompt", text(), optional=True),
    Rule("negative_prompt", text(), optional=True),
    Rule("context.seed", integer(0, MAX_SEED)),
    Rule("context.index", integer(0)),
    Rule("context.frames", integer(0, 1000)),
    Rule("guidance.scale", number(0, 100)),
    Rule("guidance.text_scale", number(0, 100), optional=True),
    Rule("token_sampler.picker.temperature", number(0, 100, low_open=True)),
    Rule("token_sampler.picker.k", integer(1)),
    Rule("token_sampler.picker.p", number(0, 1, low_open=True)),
    Rule("token_sampler.decode_step", one_of("eager", "static", "compiled")),
    Rule("token_sampler.tokens_per_call", integer(1, 10_000)),
    Rule("decoder_blend.probability", number(0, 1)),
    Rule("decoder_blend.weight", number(0, 1)),
    Rule("model.guidance.scale", number(0, 100)),
    Rule("model.steps", integer(1, 1000)),
    Rule("model.chunks", integer(1, 1000)),
    Rule("model.edit_strength", number(0, 1)),
    Rule("model.sampler.steps", integer(1, 10_000)),
    Rule("controllability.contexts", integer(1)),
    Rule("controllability.text_repeats", integer(1)),
    Rule("controllability.floor_repeats", integer(1)),
    Rule("controllability.real_clips", integer(1)),
    Rule("evaluate.contexts", integer(1)),
)

TRAIN_RULES = (
    Rule("seed", integer(0, MAX_SEED)),
    Rule("model.optim.lr", number(0, 10, low_open=True)),
    Rule("model.optim.weight_decay", number(0, 10)),
    Rule("trainer.max_steps", integer(-1)),
    Rule("trainer.max_epochs", integer(-1), optional=True),
    Rule("trainer.accumulate_grad_batches", integer(1)),
    Rule("trainer.gradient_clip_val", number(0), optional=True),
)


def check_settings(cfg: DictConfig, rules: tuple[Rule, ...]) -> None:
    """Raise SettingError for the first rule `cfg` breaks: `<key>=<value>: expected <range>`."""
    for rule in rules:
        found, value = lookup(cfg, rule.key)
        if not found or (value is None and rule.optional):
            continue
        expected = rule.check(value)
        if expected is not None:
            shown = repr(value) if not isinstance(value, str) or len(value) <= 60 else f"<{len(value)} characters>"
            raise SettingError(f"{rule.key}={shown}: expected {expected}")


def lookup(cfg: DictConfig, key: str) -> tuple[bool, Any]:
    """(whether `key` is set in `cfg`, its resolved value)."""
    node: Any = cfg
    for part in key.split("."):
        if not isinstance(node, DictConfig) or part not in node:
            return False, None
        node = node[part]
    return True, OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else node
