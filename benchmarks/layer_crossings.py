"""How often a generation climbs back up the package layers on its way from the config to frames (issue 52).

Runs `generate.py` (the entry point a user runs, through runpy) under a profiler and counts the distinct call edges
whose caller lives in a lower package than its callee (DESIGN.md §3 order: utils < weights < nn < models <
diffusion < encoders < data < viz < eval < lit < pipelines < protocols < tasks): a pipeline calling back into a
task-level function, a loader calling a function of a higher layer. Calls into the same package, into Python or
third-party code, and the first call from the entry point are not counted.

    python benchmarks/layer_crossings.py gaia1   # shipped GAIA-1 weights, one short action rollout
    python benchmarks/layer_crossings.py gaia2   # shipped GAIA-2 weights, the demo rollout with a car cut in

Prints the count and every edge (caller → callee, as package.module:function), then the functions the run called
that take the whole config (`cfg`), by package: how far the config travels down the layers.
"""

from __future__ import annotations

import runpy
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ORDER = ["utils", "weights", "nn", "models", "diffusion", "encoders", "data", "viz", "eval", "lit", "pipelines",
         "protocols", "tasks"]
RUNS = {
    "gaia1": ["mode=action", "weights=gaia1", "speed=brake", "seconds=0.5", "context.frames=2", "upsample=0",
              "video_decoder=false", "token_sampler.progress=false"],
    "gaia2": ["model=gaia2", "mode=rollout", "weights=gaia2", "data=synthetic_rig", "model.chunks=1",
              "model.sampler.steps=2", "model.sampler.progress=false", "num_futures=1", "model.guidance.scale=3",
              "model.add_agents=[{category: car, centre: [9, 0, 0.75], size: [4.5, 1.9, 1.5]}]"],
}


def where(code) -> tuple[int, str] | None:
    """(layer rank, package.module:function) of a code object inside gaia_app, else None."""
    path = Path(code.co_filename)
    parts = path.parts
    if "gaia_app" not in parts:
        return None
    inside = parts[parts.index("gaia_app") + 1:]
    if len(inside) < 2 or inside[0] not in ORDER:
        return None
    return ORDER.index(inside[0]), f"{'.'.join(inside)[:-3]}:{code.co_name}"


def crossings(overrides: list[str]) -> tuple[set[tuple[str, str]], set[str]]:
    """(the upward call edges, the gaia_app functions taking `cfg`) of one generate.py run."""
    edges: set[tuple[str, str]] = set()
    takes_cfg: set[str] = set()

    def profile(frame, event, arg) -> None:
        if event != "call" or frame.f_back is None:
            return
        callee, caller = where(frame.f_code), where(frame.f_back.f_code)
        if callee and "cfg" in frame.f_code.co_varnames[:frame.f_code.co_argcount]:
            takes_cfg.add(callee[1])
        if callee and caller and caller[0] < callee[0]:
            edges.add((caller[1], callee[1]))

    with tempfile.TemporaryDirectory() as out:
        sys.argv = ["generate.py", *overrides, f"hydra.run.dir={out}", "extras.print_config=false"]
        sys.setprofile(profile)
        try:
            runpy.run_path(str(ROOT / "generate.py"), run_name="__main__")
        except SystemExit as done:
            if done.code:
                raise
        finally:
            sys.setprofile(None)
    return edges, takes_cfg


def main() -> None:
    family = sys.argv[1] if len(sys.argv) > 1 else "gaia2"
    if family not in RUNS:
        raise SystemExit(f"family {family!r}: expected one of {sorted(RUNS)}")
    edges, takes_cfg = crossings(RUNS[family])
    print(f"{family}: {len(edges)} upward call edges")
    for caller, callee in sorted(edges):
        print(f"  {caller} → {callee}")
    print(f"{len(takes_cfg)} functions called with the whole config:")
    for package in ORDER:
        names = sorted(name for name in takes_cfg if name.split(".")[0] == package)
        if names:
            print(f"  {package} ({len(names)}): {', '.join(names)}")


if __name__ == "__main__":
    main()
