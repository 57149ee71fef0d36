"""No-op stand-ins for rerun-sdk and PyAV on a GPU lease machine, which has neither and where their wheels do not fit
the working tree that travels (docs/benchmarks.md, "GPU: one H200"). With this folder first on PYTHONPATH, modules
that import them at the top load; every attribute and call is a no-op, so nothing is logged or written through them.
Only for runs that never log to Rerun nor read or write video: token caches of synthetic clips, training with
logger=csv (benchmarks/gpu_road_users.py)."""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import sys
import types
from typing import Any


class NoOp:
    """Any attribute, call, or context of it is another no-op."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        pass

    def __call__(self, *args: Any, **kwargs: Any) -> NoOp:
        return NoOp()

    def __getattr__(self, name: str) -> NoOp:
        return NoOp()

    def __enter__(self) -> NoOp:
        return self

    def __exit__(self, *args: Any) -> bool:
        return False


def module_getattr(name: str) -> type[NoOp]:
    """A module's attributes are the NoOp class, so `rr.Image(...)` and `class X(rr.Archetype)` both work."""
    return NoOp


class SubmoduleFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """`import <package>.<anything>` gives an empty module whose attributes are no-ops."""

    def __init__(self, package: str) -> None:
        self.package = package

    def find_spec(self, name: str, path: Any = None, target: Any = None) -> importlib.machinery.ModuleSpec | None:
        if name.startswith(self.package + "."):
            return importlib.machinery.ModuleSpec(name, self, is_package=True)
        return None

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> types.ModuleType:
        module = types.ModuleType(spec.name)
        module.__getattr__ = module_getattr
        module.__path__ = []
        return module

    def exec_module(self, module: types.ModuleType) -> None:
        return None


def stub(package: types.ModuleType) -> None:
    """Make `package` (the stand-in's own module) and all its submodules no-ops."""
    package.__getattr__ = module_getattr
    sys.meta_path.insert(0, SubmoduleFinder(package.__name__))
