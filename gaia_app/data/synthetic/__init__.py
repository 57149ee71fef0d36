"""The built-in procedural multi-camera driving world (DESIGN.md §5).

    from gaia_app.data.synthetic import SyntheticClipDataset, generate_clip
    clip = generate_clip(seed=123, height=64, width=112, cameras=["front"], clip_len=8, fps=25.0)

See docs/synthetic.md for the world, its knobs, labels and the benchmark.
"""

from gaia_app.data.synthetic.dataset import SyntheticClipDataset
from gaia_app.data.synthetic.generate import SyntheticSample, WorldConfig, generate_clip, generate_sample
from gaia_app.data.synthetic.policy import BEHAVIOURS
from gaia_app.data.synthetic.road import Curve, Junction, Straight
from gaia_app.data.synthetic.scenario import ENVIRONMENTS, TIMES_OF_DAY, WEATHERS, Scenario
from gaia_app.data.synthetic.traffic import AgentSpec

__all__ = ["SyntheticClipDataset", "SyntheticSample", "WorldConfig", "generate_clip", "generate_sample", "Scenario",
           "AgentSpec", "Straight", "Curve", "Junction", "BEHAVIOURS", "ENVIRONMENTS", "WEATHERS", "TIMES_OF_DAY"]
