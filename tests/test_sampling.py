"""Balanced sampling (GAIA-1 §3): exponent 1 flattens a skewed feature, exponent 0 leaves it."""

from __future__ import annotations

import numpy as np
import pytest

from gaia_app.data.sampling import BalancedSampler, balancing_weights, bin_feature


def skewed_weather(n: int = 4000) -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.choice(["clear", "rain", "fog", "snow"], size=n, p=[0.7, 0.2, 0.07, 0.03])


def sampled_shares(features: dict, bins: dict, exponent: float, key: str, n: int = 20000) -> dict:
    sampler = BalancedSampler(balancing_weights(features, bins, exponent), num_samples=n, seed=1)
    values = np.asarray(features[key])[list(iter(sampler))]
    return {v: float(np.mean(values == v)) for v in np.unique(features[key])}


def test_exponent_one_makes_categories_uniform() -> None:
    shares = sampled_shares({"weather": skewed_weather()}, {"weather": None}, 1.0, "weather")
    assert all(abs(s - 0.25) < 0.02 for s in shares.values()), shares


def test_exponent_zero_keeps_the_empirical_distribution() -> None:
    weather = skewed_weather()
    shares = sampled_shares({"weather": weather}, {"weather": None}, 0.0, "weather")
    assert shares["clear"] == pytest.approx(np.mean(weather == "clear"), abs=0.02)
    assert shares["snow"] == pytest.approx(np.mean(weather == "snow"), abs=0.01)


def test_half_exponent_lies_between() -> None:
    shares = sampled_shares({"weather": skewed_weather()}, {"weather": None}, 0.5, "weather")
    assert 0.25 < shares["clear"] < 0.7 and 0.03 < shares["snow"] < 0.25


def test_numeric_feature_binned_and_joint_product() -> None:
    rng = np.random.default_rng(2)
    speed = np.concatenate([rng.uniform(0, 10, 3000), rng.uniform(10, 40, 1000)])
    weather = skewed_weather(len(speed))
    weights = balancing_weights({"speed": speed, "weather": weather}, {"speed": [0, 10, 40], "weather": None}, 1.0)
    slow_clear = (speed < 10) & (weather == "clear")
    fast_snow = (speed >= 10) & (weather == "snow")
    # the rare combination gets the largest weight, the common one the smallest
    assert weights[fast_snow].min() > weights[slow_clear].max()


def test_bin_feature_equal_width_and_categorical() -> None:
    assert bin_feature([0.0, 0.5, 1.0], 2).tolist() == [0, 1, 1]
    assert bin_feature(["b", "a", "b"], None).tolist() == [1, 0, 1]


def test_sampler_is_reproducible_and_epochs_differ() -> None:
    w = balancing_weights({"weather": skewed_weather(100)}, {"weather": None}, 0.5)
    a, b = BalancedSampler(w, seed=3), BalancedSampler(w, seed=3)
    first = list(iter(a))
    assert first == list(iter(b))
    assert list(iter(a)) != first


def test_bad_inputs_are_named() -> None:
    with pytest.raises(ValueError, match="different lengths"):
        balancing_weights({"a": [1, 2], "b": [1]}, {}, 0.5)
    with pytest.raises(ValueError, match="NaN"):
        bin_feature([1.0, float("nan")], 4)
