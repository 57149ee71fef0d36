"""House rule (DESIGN.md §3): imports point one way, package by package; nn/models/diffusion never import Lightning
or Hydra. Each package lists the packages it may import: a new arrow (models → data, nn → models, pipelines → lit)
fails here until the design says it is right."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "gaia_app"
BELOW_MODELS = {"nn", "utils"}
# package → the gaia_app packages it may import (besides itself), as in DESIGN.md §3: nn ← models, diffusion (sees
# nets through protocols) ← lit ← pipelines ← protocols ← tasks; data, eval, encoders below pipelines; weights
# (loading: checkpoints, weights folders, the _target_ allow-list) just above utils; utils at the floor. Inference
# never builds a LightningModule, so pipelines do not import lit; evaluation protocols do not import tasks.
ALLOWED = {
    "utils": set(),
    "weights": {"utils"},
    "nn": {"utils"},
    "models": BELOW_MODELS,
    "diffusion": BELOW_MODELS,
    "encoders": BELOW_MODELS,
    "data": {"utils"},
    "viz": {"data", "utils"},
    "eval": {"nn", "models", "diffusion", "encoders", "data", "weights", "utils"},
    "lit": {"nn", "models", "diffusion", "encoders", "data", "eval", "viz", "weights", "utils"},
    "pipelines": {"nn", "models", "diffusion", "encoders", "data", "eval", "viz", "weights", "utils"},
    "protocols": {"nn", "models", "diffusion", "encoders", "data", "eval", "viz", "weights", "utils", "lit",
                  "pipelines"},
    "tasks": {"nn", "models", "diffusion", "encoders", "data", "eval", "viz", "weights", "utils", "lit", "pipelines",
              "protocols"},
}
LAYER = ALLOWED
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
            if target in ALLOWED and target != layer:
                assert target in ALLOWED[layer], f"{path} ({layer}) must not import {name} ({target}): " \
                                                 f"{layer} may import {sorted(ALLOWED[layer])}"


def test_the_allowed_imports_have_no_cycle() -> None:
    """The table itself points one way: no package may reach itself through the packages it may import."""
    def reach(start: str) -> set[str]:
        seen, todo = set(), list(ALLOWED[start])
        while todo:
            package = todo.pop()
            if package not in seen:
                seen.add(package)
                todo += ALLOWED[package]
        return seen

    assert all(package not in reach(package) for package in ALLOWED)


def test_every_subpackage_is_checked() -> None:
    found = {p.name for p in PACKAGE.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert found <= set(LAYER), f"new subpackages need a layer in this test: {found - set(LAYER)}"



def test_samplers_depend_on_protocols_not_on_models() -> None:
    """diffusion/ holds samplers and schedules: it sees a model through the few methods it calls (the protocols in
    ar_sampling.py and video_sampling.py), never by importing gaia_app.models, so a new model plugs in unchanged."""
    for path in sorted((PACKAGE / "diffusion").glob("*.py")):
        bad = [name for name in imports_of(path) if name.startswith("gaia_app.models")]
        assert not bad, f"{path.name} imports {bad}"


def test_benchmarks_never_import_tasks() -> None:
    """DESIGN.md §3: benchmarks/ run the evaluation protocols (gaia_app/protocols) as generate.py does, never its
    task layer, so a protocol has one home that both use."""
    for path in sorted((PACKAGE.parent / "benchmarks").glob("*.py")):
        bad = [name for name in imports_of(path) if name == "gaia_app.tasks" or name.startswith("gaia_app.tasks.")]
        assert not bad, f"benchmarks/{path.name} imports {bad}"


def test_the_longest_modules_listed_for_the_workers_exist() -> None:
    """tests/conftest.py hands these modules out first under `make test`; a misspelt or removed one would silently
    drop out of the order."""
    from tests.conftest import LONGEST_MODULES, ROOT

    missing = [name for name in LONGEST_MODULES if not (ROOT / "tests" / name).is_file()]
    assert not missing and len(set(LONGEST_MODULES)) == len(LONGEST_MODULES), missing
