"""GAIA-1 tokenizer training (GAIA-1 §2.2, §4.1) through Lightning with manual generator/discriminator optimisation."""

from __future__ import annotations

import functools
import logging
from pathlib import Path

import lightning as L
import pytest
import torch
import torch.nn.functional as F
from omegaconf import DictConfig
from torch.utils.data import DataLoader, Dataset

from gaia_app.encoders import load_perceptual, load_vision_teacher
from gaia_app.lit.gaia1_tokenizer import ImageTokenizerModule
from gaia_app.lit.schedules import warmup_cosine
from gaia_app.models.gaia1.tokenizer import ImageTokenizer
from gaia_app.nn.discriminator import PatchDiscriminator
from gaia_app.nn.vgg import VGG16Features
from gaia_app.nn.vit import VisionTransformer

VIT = dict(embed_dim=32, depth=1, num_heads=2)
TINY_NET = functools.partial(ImageTokenizer, channels=8, channel_mults=(1, 2, 2), blocks_per_stage=1, latent_dim=16,
                             codebook_size=32, code_dim=8, distill_dim=VIT["embed_dim"])
TINY_DISC = functools.partial(PatchDiscriminator, channels=8, num_layers=2)


class FixedBatch(Dataset):
    """The same four smooth 32×32 images forever: low-resolution noise, upsampled."""

    def __init__(self) -> None:
        low = torch.rand(4, 3, 4, 4, generator=torch.Generator().manual_seed(0)) * 2 - 1
        self.images = F.interpolate(low, size=(32, 32), mode="bilinear", align_corners=False)

    def __len__(self) -> int:
        return 1_000_000

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return {"image": self.images[i % 4]}


class RecordSteps(L.Callback):
    """Keeps each batch's loss terms and a copy of the discriminator's first weight."""

    def __init__(self) -> None:
        self.terms: list[dict[str, float]] = []
        self.disc_weights: list[torch.Tensor] = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self.terms.append({k: float(v) for k, v in outputs.items()})
        self.disc_weights.append(pl_module.discriminator.layers[0].weight.detach().clone())


@pytest.fixture(scope="module")
def frozen_checkpoints(tmp_path_factory) -> dict[str, Path]:
    """Small randomly initialised VGG16-layout trunk and DINO-layout ViT, saved like the real checkpoints."""
    root = tmp_path_factory.mktemp("pretrained")
    torch.manual_seed(0)
    torch.save(VGG16Features(base_width=8).state_dict(), root / "vgg16_features.pth")
    torch.save(VisionTransformer(**VIT).state_dict(), root / "dino.pth")
    return {"perceptual": root / "vgg16_features.pth", "dino": root / "dino.pth"}


def make_module(frozen: dict[str, Path] | None = None, **kw) -> ImageTokenizerModule:
    torch.manual_seed(0)
    teachers = {}
    if frozen:
        teachers = {"perceptual": functools.partial(load_perceptual, checkpoint=frozen["perceptual"], base_width=8),
                    "dino": functools.partial(load_vision_teacher, checkpoint=frozen["dino"], **VIT)}
    args = dict(net=TINY_NET, optim=functools.partial(torch.optim.AdamW, lr=3e-3, weight_decay=0.01, betas=(0.5, 0.9)),
                discriminator=TINY_DISC, **teachers)
    return ImageTokenizerModule(**{**args, **kw})


def fit(module: ImageTokenizerModule, steps: int, **trainer_kw) -> tuple[L.Trainer, RecordSteps]:
    record = RecordSteps()
    trainer = L.Trainer(max_steps=steps, accelerator="cpu", logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, callbacks=[record], **trainer_kw)
    trainer.fit(module, DataLoader(FixedBatch(), batch_size=4))
    return trainer, record


def test_gan_starts_at_the_configured_step() -> None:
    """Before gan_start_step: no discriminator update and no GAN term; from it on: both, every batch."""
    sched = functools.partial(warmup_cosine, warmup_steps=1, decay_steps=10, final_lr=1e-4)
    module = make_module(gan_start_step=2, sched=sched)
    module.configure_model()
    initial = module.discriminator.layers[0].weight.detach().clone()
    trainer, record = fit(module, steps=4)
    for step in (0, 1):
        assert "gan" not in record.terms[step] and "disc_loss" not in record.terms[step]
        assert torch.equal(record.disc_weights[step], initial)
        terms = record.terms[step]
        assert terms["loss"] == pytest.approx(terms["l1"] + terms["l2"] + terms["codebook"], rel=1e-6)
    for step in (2, 3):
        assert {"gan", "adaptive_weight", "disc_loss"} <= set(record.terms[step])
        assert not torch.equal(record.disc_weights[step], record.disc_weights[step - 1])
    # Lightning's step counter stays one per batch; the discriminator's schedule counts its own 2 steps
    assert trainer.global_step == 4
    generator_sched, disc_sched = (c.scheduler for c in trainer.lr_scheduler_configs)
    assert (generator_sched.last_epoch, disc_sched.last_epoch) == (4, 2)


def test_adaptive_weight_balances_gradients_at_the_decoder_output() -> None:
    module = make_module()
    module.configure_model()
    image = FixedBatch().images
    terms = module.generator_terms(image, module.tokenizer(image), with_gan=True)
    assert terms["adaptive_weight"].item() > 0
    gan = -module.discriminator(module.tokenizer(image).reconstruction).mean()
    assert terms["gan"].item() == pytest.approx(module.weights.gan * terms["adaptive_weight"].item() * gan.item(),
                                                rel=1e-4)
    assert terms["loss"].item() == pytest.approx(sum(terms[k].item() for k in ("l1", "l2", "codebook", "gan")),
                                                 rel=1e-5)


def test_none_switches_losses_off_with_warnings(caplog) -> None:
    # CLI value, `encoder=none` node, null
    module = make_module(perceptual="none", dino=DictConfig({}), discriminator=None)
    with caplog.at_level(logging.WARNING, logger="gaia_app.lit.gaia1_tokenizer"):
        module.load_frozen_networks()
    messages = " | ".join(r.getMessage() for r in caplog.records)
    for text in ("model.perceptual=none", "model.dino=none", "model.discriminator=null"):
        assert text in messages
    module.configure_model()
    assert module.discriminator is None
    image = FixedBatch().images
    assert set(module.losses(image, module.tokenizer(image))) == {"l1", "l2", "codebook", "loss"}


def test_a_value_that_is_not_a_factory_is_refused() -> None:
    with pytest.raises(TypeError, match="model.dino=none"):
        make_module(dino="dino_vits16")


def test_frozen_networks_stay_out_of_the_checkpoint(frozen_checkpoints) -> None:
    module = make_module(frozen_checkpoints)
    module.configure_model()
    module.load_frozen_networks()
    state = module.state_dict()
    assert not any(k.startswith(("frozen", "perceptual", "dino")) or ".vit." in k or ".trunk." in k for k in state)
    assert all(p.requires_grad for p in module.parameters())  # nothing frozen is registered as a parameter
    # the checkpoint loads into a module whose teacher files are gone: they are only read when fitting starts
    gone = make_module({"perceptual": Path("/nonexistent/vgg.pth"), "dino": Path("/nonexistent/dino.pth")})
    gone.configure_model()
    gone.load_state_dict(state, strict=True)


def test_trainer_gradient_clipping_is_refused_with_the_keys_to_change() -> None:
    with pytest.raises(ValueError, match="trainer.gradient_clip_val=null"):
        fit(make_module(), steps=1, gradient_clip_val=1.0)


def test_tokenizer_learns_with_gan_perceptual_and_dino(frozen_checkpoints) -> None:
    """All GAIA-1 §4.1 losses on (tiny random perceptual and DINO nets): the fixed batch's L1 falls ≥ 3× in 100
    steps."""
    sched = functools.partial(warmup_cosine, warmup_steps=5, decay_steps=100, final_lr=3e-4)
    module = make_module(frozen_checkpoints, sched=sched, gan_start_step=30)
    trainer, record = fit(module, steps=100)
    assert trainer.global_step == 100
    assert all(k in record.terms[-1] for k in ("perceptual", "dino", "gan", "disc_loss"))
    l1 = [t["l1"] / module.weights.l1 for t in record.terms]
    final = sum(l1[-5:]) / 5
    assert final < l1[0] / 3, (l1[0], final)
    assert record.terms[-1]["dino"] < record.terms[0]["dino"]


def test_loss_weights_from_config_are_the_ones_applied(tmp_path) -> None:
    """λ values given as Hydra overrides reach the loss terms unchanged (GAIA-1 §4.1 defaults otherwise)."""
    from hydra.utils import instantiate

    from tests.conftest import compose_config

    cfg = compose_config("train", ["model=gaia1_tokenizer_tiny", "model.weights.l1=0.7", "model.weights.l2=3.0",
                                   "model.weights.codebook=0.5"], tmp_path)
    module = instantiate(cfg.model)
    module.configure_model()
    torch.manual_seed(0)
    image = torch.rand(2, 3, 16, 16) * 2 - 1
    out = module.tokenizer(image)
    terms = module.generator_terms(image, out, with_gan=False)
    assert torch.allclose(terms["l1"], 0.7 * torch.nn.functional.l1_loss(out.reconstruction, image))
    assert torch.allclose(terms["l2"], 3.0 * torch.nn.functional.mse_loss(out.reconstruction, image))
    assert torch.allclose(terms["codebook"], 0.5 * (out.codebook_loss + out.commitment_loss))
    defaults = instantiate(compose_config("train", ["model=gaia1_tokenizer"], tmp_path).model).weights
    assert ((defaults.l1, defaults.l2, defaults.perceptual, defaults.gan, defaults.codebook, defaults.dino)
            == (0.2, 2.0, 0.1, 1.0, 1.0, 0.1))


class BoxedBatch(FixedBatch):
    """FixedBatch with an agent box in the top-left quarter of every image."""

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        box = torch.zeros(32, 32, dtype=torch.bool)
        box[:8, :8] = True
        return {"image": self.images[i % 4], "agent_box": box}


def box_error(module: ImageTokenizerModule) -> tuple[float, float]:
    """Mean squared error of the reconstruction inside and outside the box of BoxedBatch."""
    batch = {k: torch.stack([BoxedBatch()[i][k] for i in range(4)]) for k in ("image", "agent_box")}
    with torch.no_grad():
        err = (module.tokenizer(batch["image"]).reconstruction - batch["image"]).pow(2).mean(dim=1)
    return float(err[batch["agent_box"]].mean()), float(err[~batch["agent_box"]].mean())


def test_agent_weight_scales_the_pixels_inside_boxes() -> None:
    module = make_module(weights={"agents": 9.0})
    image = FixedBatch().images
    box = torch.zeros(4, 32, 32, dtype=torch.bool)
    box[:, :16, :16] = True  # a quarter of the pixels
    weights = module.pixel_weights(image, box)
    assert weights.mean().item() == pytest.approx(1.0)
    inside, outside = weights[:, 0][box].unique(), weights[:, 0][~box].unique()
    assert len(inside) == len(outside) == 1 and (inside / outside).item() == pytest.approx(10.0)
    assert make_module().pixel_weights(image, box) is None  # weight 0: GAIA-1's plain L1/L2
    with pytest.raises(ValueError, match="data.agent_boxes=true"):
        module.pixel_weights(image, None)
    with pytest.raises(ValueError, match=r"'agent_box' \(4, 16, 16\) does not match"):
        module.pixel_weights(image, box[:, :16, :16])


def test_agent_weight_buys_accuracy_inside_boxes() -> None:
    """The same tiny fit with and without the weight: weighting spends the codes on the boxed pixels, whose error
    falls below the plain run's by a clear factor."""
    errors = {}
    for agents in (0.0, 30.0):
        module = make_module(discriminator=None, weights={"agents": agents})
        trainer = L.Trainer(max_steps=60, accelerator="cpu", logger=False, enable_checkpointing=False,
                            enable_progress_bar=False, enable_model_summary=False, callbacks=[])
        trainer.fit(module, DataLoader(BoxedBatch(), batch_size=4))
        errors[agents] = box_error(module)
    assert errors[30.0][0] < 0.5 * errors[0.0][0], errors
