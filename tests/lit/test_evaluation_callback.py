"""EvaluationCallback: metrics from `evaluation_pair` stream over validation batches and reach the loggers."""

from __future__ import annotations

import lightning.pytorch as pl
import pytest
import torch
from torch.utils.data import DataLoader, TensorDataset

from gaia_app.lit.evaluation import EvaluationCallback


class PairModule(pl.LightningModule):
    """Validation batches are videos; the 'generated' side is the batch plus `noise` × a fixed noise field."""

    def __init__(self, noise: float, with_pair: bool = True):
        super().__init__()
        self.noise, self.layer = noise, torch.nn.Linear(1, 1)
        if not with_pair:
            self.evaluation_pair = None

    def validation_step(self, batch, batch_idx):
        return None

    def evaluation_pair(self, batch):
        (video,) = batch
        g = torch.Generator().manual_seed(0)
        return video, (video + self.noise * torch.randn(video.shape, generator=g)).clamp(-1, 1)


def videos() -> DataLoader:
    g = torch.Generator().manual_seed(1)
    base = torch.nn.functional.avg_pool2d(torch.rand(8, 3, 40, 72, generator=g) * 2 - 1, 5, 1, 2)
    clips = torch.stack([torch.roll(base, shifts=(0, i), dims=(-2, -1))[:, :, 4:36, 4:68] for i in range(5)], dim=1)
    return DataLoader(TensorDataset(clips), batch_size=4)  # 2 batches of (4, 5, 3, 32, 64)


def validate(module: pl.LightningModule, callback: EvaluationCallback, tmp_path) -> dict[str, float]:
    trainer = pl.Trainer(default_root_dir=tmp_path, logger=pl.loggers.CSVLogger(tmp_path), callbacks=[callback],
                         enable_progress_bar=False, enable_model_summary=False, accelerator="cpu")
    return trainer.validate(module, videos(), verbose=False)[0]


def test_identical_pairs_score_perfectly_and_noise_worse(tmp_path) -> None:
    metrics = ["psnr", "ssim", "fvmd"]
    same = validate(PairModule(0.0), EvaluationCallback(metrics), tmp_path / "same")
    noisy = validate(PairModule(0.3), EvaluationCallback(metrics), tmp_path / "noisy")
    assert same["eval/ssim"] == pytest.approx(1.0) and same["eval/fvmd"] == pytest.approx(0.0, abs=1e-9)
    assert same["eval/psnr"] > 90 and noisy["eval/psnr"] < 25
    assert noisy["eval/ssim"] < 0.9 and noisy["eval/fvmd"] > 0.1
    assert (tmp_path / "noisy" / "lightning_logs" / "version_0" / "metrics.csv").read_text().count("eval/fvmd") == 1


def test_max_batches_limits_the_work(tmp_path) -> None:
    callback = EvaluationCallback(["psnr"], max_batches=1)
    seen = []
    module = PairModule(0.1)
    original = module.evaluation_pair
    module.evaluation_pair = lambda batch: seen.append(1) or original(batch)
    validate(module, callback, tmp_path)
    assert len(seen) == 1


def test_bad_settings_are_named(tmp_path) -> None:
    with pytest.raises(ValueError, match=r"metrics=\['fvd'\]: choose from"):
        EvaluationCallback(["fvd"])
    with pytest.raises(ValueError, match="set callbacks.evaluation.fid_checkpoint"):
        EvaluationCallback(["fid"])
    with pytest.raises(ValueError, match="set callbacks.evaluation.fdd_checkpoint"):
        EvaluationCallback(["fdd"])
    with pytest.raises(TypeError, match="PairModule has no evaluation_pair"):
        validate(PairModule(0.0, with_pair=False), EvaluationCallback(["psnr"]), tmp_path)


def test_lpips_from_local_vgg_weights(tmp_path) -> None:
    from gaia_app.nn.vgg import VGG16Features

    torch.manual_seed(0)
    torch.save(VGG16Features().state_dict(), tmp_path / "vgg16_features.pth")

    def callback() -> EvaluationCallback:
        return EvaluationCallback(["lpips"], max_batches=1, lpips_checkpoint=str(tmp_path / "vgg16_features.pth"))

    same = validate(PairModule(0.0), callback(), tmp_path / "same")
    noisy = validate(PairModule(0.3), callback(), tmp_path / "noisy")
    assert same["eval/lpips"] == pytest.approx(0.0, abs=1e-6) and noisy["eval/lpips"] > 0.01
    with pytest.raises(ValueError, match="set callbacks.evaluation.lpips_checkpoint"):
        EvaluationCallback(["lpips"])
