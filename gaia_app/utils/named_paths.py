"""`NAME=PATH` command-line arguments, as the report protocols take them (`--model shipped=<folder>`)."""

from __future__ import annotations

from pathlib import Path


def parse_named_paths(specs: list[str], flag: str, placeholder: str = "PATH") -> dict[str, Path]:
    """{name: path} of `NAME=PATH` specs, in order. Errors name the flag: a spec without both parts, a name given
    twice, a path that does not exist."""
    paths: dict[str, Path] = {}
    for spec in specs:
        name, sep, path = spec.partition("=")
        if not sep or not name or not path:
            raise ValueError(f"{flag} {spec!r}: expected NAME={placeholder}")
        if name in paths:
            raise ValueError(f"{flag}: the name {name!r} is given twice")
        if not Path(path).exists():
            raise FileNotFoundError(f"{flag} {name}: {path} does not exist")
        paths[name] = Path(path)
    return paths
