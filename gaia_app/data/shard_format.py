"""Names shared by the shard writer (gaia_app/data/shard.py) and the streaming readers (gaia_app/data/shards.py)."""

from __future__ import annotations

import re

KINDS = ("clips", "tokens", "latents")
INDEX = "shards.json"
PLAN = ".plan.json"


def shard_name(split: str, number: int) -> str:
    """`train-000007.tar`: the split's shards, numbered in write order."""
    return f"{split}-{number:06d}.tar"


def features_file(split: str) -> str:
    return f"features-{split}.npz"


def encode_name(name: str, slash: bool = False) -> str:
    """A key or file name that WebDataset splits back exactly: it cuts a member name at the first `.` of its last
    path component, an extension may hold no `/`, and it lowercases the extension (the sample's file names).
    `%` → `%25`; keys: `.` → `%2E`; file names: `/` → `%2F` and each capital letter → `%` + its hex code
    (`CAM_FRONT.mp4` → `%43%41%4D_%46%52%4F%4E%54.mp4`), so every camera name a clip folder allows round-trips."""
    name = name.replace("%", "%25")
    if not slash:
        return name.replace(".", "%2E")
    return re.sub(r"[A-Z]", lambda m: f"%{ord(m.group()):02X}", name).replace("/", "%2F")


def decode_name(name: str) -> str:
    """The inverse of `encode_name`, also after WebDataset lowercased the escapes' hex digits."""
    return re.sub(r"%([0-9A-Fa-f]{2})", lambda m: chr(int(m.group(1), 16)), name)
