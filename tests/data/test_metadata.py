"""Metadata vocabularies for the GAIA-2 world model's metadata tokens."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from gaia_app.data.metadata import MetadataEncoder, vocabulary_size
from tests.conftest import CONF_DIR


def test_known_unknown_and_other_values() -> None:
    enc = MetadataEncoder(["weather", "speed_limit", "lane_types", "traffic_light", "crossing"])
    meta = {"weather": "rain", "speed_limit": 70.0, "lane_types": ["solid", "dashed", "dashed"], "traffic_light": None,
            "crossing": False}
    assert enc.encode(meta, {"traffic_light": "green"}) == {"weather": 2, "speed_limit": 6, "lane_types": 2,
                                                            "traffic_light": 3, "crossing": 1}
    assert enc.encode({"weather": "sandstorm"})["weather"] == vocabulary_size("weather") - 1  # "other"
    assert enc.encode({})["crossing"] == 0  # unknown
    assert enc.report["weather:other(sandstorm)"] == 1 and enc.report["crossing:unknown"] == 2
    batch = enc.batch([meta, {"weather": "snow"}])
    assert batch["weather"].tolist() == [2, 4]


def test_unknown_field_is_refused() -> None:
    with pytest.raises(KeyError, match="metadata field 'mood' has no vocabulary"):
        MetadataEncoder(["mood"])


def test_model_presets_use_the_vocabulary_sizes() -> None:
    for path in (CONF_DIR / "model" / "net").glob("gaia2_world_model_*.yaml"):
        fields = OmegaConf.load(path).metadata_fields
        assert {name: vocabulary_size(name) for name in fields} == dict(fields), path.name
