"""Metadata vocabularies: clip metadata values → integer indices for the GAIA-2 world model's metadata tokens.

GAIA-2 conditions on country, weather, time of day, speed limit, lane count and types, traffic-light
state, intersection type and crossings (GAIA-2 report, world model). Each field has a fixed vocabulary
here; index 0 is "unknown" (the field is absent or null in the clip) and the last index is "other" (a
value outside the vocabulary). Both are counted by `MetadataEncoder.report`, so nothing is mapped away
silently. Numeric fields (speed limit, lanes) are bucketed.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping, Sequence
from typing import Any

import torch

# field → known values (index = position + 1; 0 unknown, len + 1 other)
VOCABULARIES: dict[str, tuple[str, ...]] = {
    "weather": ("clear", "rain", "fog", "snow"),
    "time_of_day": ("day", "dusk", "night"),
    "country": ("GB", "US", "DE", "JP", "FR", "NL"),
    "lane_types": ("solid", "dashed", "double", "bus", "cycle", "none"),
    "traffic_light": ("red", "amber", "green"),
    "intersection": ("junction", "roundabout", "t_junction"),
    "crossing": ("False", "True"),
}
# numeric fields: bucket edges (value < edges[0] → bucket 1, …, ≥ edges[-1] → last bucket)
BUCKETS: dict[str, tuple[float, ...]] = {
    "speed_limit": (25, 35, 45, 55, 65, 75, 85, 95, 105, 115),
    "lanes": (1.5, 2.5, 3.5, 4.5, 5.5),
}


def vocabulary_size(name: str) -> int:
    """Indices of field `name`: unknown + values + other, or unknown + buckets."""
    if name in VOCABULARIES:
        return len(VOCABULARIES[name]) + 2
    if name in BUCKETS:
        return len(BUCKETS[name]) + 2
    raise KeyError(f"metadata field '{name}' has no vocabulary; known: {sorted([*VOCABULARIES, *BUCKETS])}")


class MetadataEncoder:
    """Encodes clip metadata dicts for the fields a model was built with.

    Lists (e.g. lane types per lane) are encoded by their most frequent value; per-frame fields
    (traffic_light) take the value of the given frame metadata when the clip-level value is null.
    """

    def __init__(self, fields: Sequence[str]):
        for name in fields:
            vocabulary_size(name)
        self.fields = list(fields)
        self.report: Counter[str] = Counter()

    def index(self, name: str, value: Any) -> int:
        if value is None:
            self.report[f"{name}:unknown"] += 1
            return 0
        if name in BUCKETS:
            edges = BUCKETS[name]
            return 1 + sum(float(value) >= edge for edge in edges)
        if isinstance(value, (list, tuple)):
            value = Counter(str(v) for v in value).most_common(1)[0][0] if value else None
            return self.index(name, value)
        vocabulary = VOCABULARIES[name]
        text = str(value)
        if text in vocabulary:
            return vocabulary.index(text) + 1
        self.report[f"{name}:other({text})"] += 1
        return len(vocabulary) + 1

    def encode(self, meta: Mapping[str, Any], frame_meta: Mapping[str, Any] | None = None) -> dict[str, int]:
        """{field: index} of one clip (clip-level values, per-frame ones as a fallback)."""
        out = {}
        for name in self.fields:
            value = meta.get(name)
            if value is None and frame_meta is not None:
                value = frame_meta.get(name)
            out[name] = self.index(name, value)
        return out

    def batch(self, metas: Sequence[Mapping[str, Any]], frame_metas: Sequence[Mapping[str, Any] | None] | None = None
              ) -> dict[str, torch.Tensor]:
        """{field: (b,) int64} for a batch of clips."""
        frame_metas = frame_metas or [None] * len(metas)
        rows = [self.encode(m, f) for m, f in zip(metas, frame_metas)]
        return {name: torch.tensor([row[name] for row in rows], dtype=torch.long) for name in self.fields}
