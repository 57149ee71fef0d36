"""benchmarks/eval_video_decoder.py on the shipped GAIA-1 weights (--weights): the rows it is asked for, paired."""
import json
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.mark.slow  # a benchmark script end to end on the shipped weights; the quick tier reaches its gaia_app lines
def test_shipped_decoder_rows_with_independent_and_antithetic_draws(tmp_path: Path, monkeypatch) -> None:
    sys.path.insert(0, str(BENCHMARKS))
    import eval_video_decoder

    monkeypatch.setattr(sys, "argv", ["eval_video_decoder.py", "--weights=gaia1", "--world-seed=31337", "--clips=2",
                                      "--frames=7", "--rows-only", "--samplers=mean2,amean2", f"--out={tmp_path}"])
    eval_video_decoder.main()
    results = json.loads((tmp_path / "results.json").read_text())
    assert list(results["samplers"]) == ["mean2", "amean2"] and "upsampling" not in results
    for row in results["samplers"].values():
        assert 5 < row["psnr"]["mean"] < 60 and row["flicker"]["mean"] >= 0
        assert "psnr_minus_framewise" in row
    assert "| amean2 |" in (tmp_path / "results.md").read_text()


def test_shipped_decoder_needs_a_world_and_an_out_folder(monkeypatch) -> None:
    sys.path.insert(0, str(BENCHMARKS))
    import eval_video_decoder

    monkeypatch.setattr(sys, "argv", ["eval_video_decoder.py", "--weights=gaia1"])
    with pytest.raises(SystemExit):
        eval_video_decoder.main()
