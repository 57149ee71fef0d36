"""No-op stand-in (benchmarks/gpu_stubs/noop_module.py)."""
import sys

from noop_module import stub

stub(sys.modules[__name__])
