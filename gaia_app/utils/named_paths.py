"""`NAME=PATH` command-line arguments, as the report protocols take them (`--model shipped=<folder>`)."""

from __future__ import annotations

from pathlib import Path


def parse_grouped_paths(specs: list[str], flag: str, placeholder: str = "PATH") -> dict[str, list[Path]]:
    """{name: [paths]} of `NAME=PATH` specs, names in first-seen order, a name given again adding a path to its group
    (`--run 1e-2=<run a> --run 1e-2=<run b>`). Errors name the flag: a spec without both parts, a path given twice,
    a path that does not exist."""
    groups: dict[str, list[Path]] = {}
    for spec in specs:
        name, sep, path = spec.partition("=")
        if not sep or not name or not path:
            raise ValueError(f"{flag} {spec!r}: expected NAME={placeholder}")
        if not Path(path).exists():
            raise FileNotFoundError(f"{flag} {name}: {path} does not exist")
        if any(Path(path) in paths for paths in groups.values()):
            raise ValueError(f"{flag} {name}: {path} is given twice")
        groups.setdefault(name, []).append(Path(path))
    return groups


def parse_named_paths(specs: list[str], flag: str, placeholder: str = "PATH") -> dict[str, Path]:
    """{name: path} of `NAME=PATH` specs, in order: as parse_grouped_paths, and a name given twice is an error."""
    groups = parse_grouped_paths(specs, flag, placeholder)
    for name, paths in groups.items():
        if len(paths) > 1:
            raise ValueError(f"{flag}: the name {name!r} is given twice")
    return {name: paths[0] for name, paths in groups.items()}
