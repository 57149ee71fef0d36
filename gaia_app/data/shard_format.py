"""Names shared by the shard writer (gaia_app/data/shard.py) and the streaming readers (gaia_app/data/shards.py)."""

from __future__ import annotations

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
    path component, and an extension may hold no `/`. `%` → `%25`, `.` → `%2E` (keys), `/` → `%2F` (file names)."""
    name = name.replace("%", "%25")
    return name.replace("/", "%2F") if slash else name.replace(".", "%2E")


def decode_name(name: str) -> str:
    """The inverse of `encode_name`."""
    return name.replace("%2F", "/").replace("%2E", ".").replace("%25", "%")
