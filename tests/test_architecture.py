"""House rule (DESIGN.md §3): imports point one way, nn/models/diffusion never import Lightning or Hydra."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "gaia_app"
LAYER = {"nn": 0, "models": 0, "diffusion": 0, "encoders": 0, "eval": 0, "data": 0, "utils": 0,
         "viz": 1, "lit": 2, "pipelines": 3, "tasks": 4}
PURE_TORCH = {"nn", "models", "diffusion"}


def imports_of(path: Path) -> list[str]:
    tree = ast.parse(path.read_text())
    names: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.append(node.module)
    return names


MODULES = sorted(p for p in PACKAGE.rglob("*.py"))


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_import_direction(path: Path) -> None:
    parts = path.relative_to(PACKAGE).parts
    if len(parts) < 2:
        return
    layer = parts[0]
    for name in imports_of(path):
        top = name.split(".")[0]
        if layer in PURE_TORCH:
            assert top not in ("lightning", "hydra", "pytorch_lightning"), f"{path}: pure-torch layer imports {name}"
        if top == "gaia_app" and "." in name:
            target = name.split(".")[1]
            if target in LAYER and layer in LAYER:
                assert LAYER[target] <= LAYER[layer], f"{path} ({layer}) must not import {name} ({target})"


def test_every_subpackage_is_checked() -> None:
    found = {p.name for p in PACKAGE.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert found <= set(LAYER), f"new subpackages need a layer in this test: {found - set(LAYER)}"



def test_samplers_depend_on_protocols_not_on_models() -> None:
    """diffusion/ holds samplers and schedules: it sees a model through the few methods it calls (the protocols in
    ar_sampling.py and video_sampling.py), never by importing gaia_app.models, so a new model plugs in unchanged."""
    for path in sorted((PACKAGE / "diffusion").glob("*.py")):
        bad = [name for name in imports_of(path) if name.startswith("gaia_app.models")]
        assert not bad, f"{path.name} imports {bad}"
