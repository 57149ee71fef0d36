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


def test_the_started_rows_run_ddim_from_a_noise_made_from_the_draw() -> None:
    sys.path.insert(0, str(BENCHMARKS))
    import eval_video_decoder
    import torch

    from gaia_app.diffusion.noise_schedule import CosineNoiseSchedule

    sampler = eval_video_decoder.sampler_for("sddim3", CosineNoiseSchedule(100))
    seen = []

    def denoise(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        seen.append(x.clone())
        return torch.zeros_like(x)

    noise = torch.randn(2, 4, 3, 5, 6)
    sampler(denoise, noise)
    assert len(seen) == 3 and sampler.inner.steps == 3
    assert torch.equal(seen[0], noise[:, :1].expand_as(noise))  # every frame starts from the first frame's noise
    assert not torch.equal(noise[:, 0], noise[:, 1])
    seen.clear()
    eval_video_decoder.sampler_for("zero", CosineNoiseSchedule(100))(denoise, noise)
    assert len(seen) == 1 and not seen[0].any()  # the "zero" row: one step from x_T = 0
    with pytest.raises(ValueError, match="sddim<k>"):
        eval_video_decoder.sampler_for("sddim", CosineNoiseSchedule(100))
