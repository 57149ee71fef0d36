"""Names that become parts of file paths: clip ids and camera names, checked wherever they are read.

A camera name from a `meta.json`, an importer's `--camera` or a config ends up in paths such as
`<out_dir>/<clip_id>/<camera>.npy` or `<clip_dir>/<camera>.mp4`. A name like `x/../../elsewhere` would read and
write outside the folder the user chose, so every name is checked to be plain, and every output path built from
names is checked to stay under its root.

Plain names: letters, digits, `_` and `-` (clip ids may also hold `.`), starting with a letter or digit. Camera
names hold no `.`, so `<camera>.actions.npy` sidecars of token caches can never be mistaken for another camera.
"""

from __future__ import annotations

import re
from pathlib import Path

from gaia_app.data.clip import ClipError

CLIP_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")
CAMERA_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]{0,63}")


def check_clip_id(name: object, where: str) -> str:
    """`name` if it is a plain clip id (a single folder name), else a ClipError naming `where`."""
    if not isinstance(name, str) or not CLIP_ID.fullmatch(name) or ".." in name:
        raise ClipError(f"{where}: clip id {name!r} is not a plain name: use letters, digits, '.', '_' and '-' "
                        "(starting with a letter or digit, no '..', at most 128 characters)")
    return name


def check_camera_name(name: object, where: str) -> str:
    """`name` if it is a plain camera name, else a ClipError naming `where`."""
    if not isinstance(name, str) or not CAMERA_NAME.fullmatch(name):
        raise ClipError(f"{where}: camera name {name!r} is not a plain name: use letters, digits, '_' and '-' "
                        "(starting with a letter or digit, at most 64 characters)")
    return name


def inside(root: str | Path, *parts: str) -> Path:
    """root / parts, refused (ClipError) unless it resolves to a path under `root`: the last guard of every output
    path built from names."""
    base = Path(root).resolve()
    path = base.joinpath(*parts).resolve()
    if path == base or base not in path.parents:
        raise ClipError(f"output path {'/'.join(parts)!r} would leave its folder {root}")
    return path
