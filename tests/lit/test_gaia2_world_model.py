"""GAIA-2 latent world model training by flow matching on latent-cache windows."""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import pytest
import torch

from gaia_app.data.clip import AgentBoxes, CameraSpec
from gaia_app.data.latent_cache import LatentClip, find_latent_clips, write_latent_clip
from gaia_app.data.latent_windows import (
    LatentCacheDataModule,
    LatentWindows,
    collate_latent_windows,
)
from gaia_app.data.metadata import MetadataEncoder
from gaia_app.data.synthetic.rig import build_rig
from gaia_app.encoders.text import LearnedTextEncoder
from gaia_app.lit.gaia2_world_model import LatentWorldModelModule, batch_conditions
from gaia_app.models.gaia2.latent_world_model import LatentWorldModel

META = {"weather": 6, "time_of_day": 5}


def write_cache(root: Path, clips: int = 3, steps: int = 6) -> None:
    """Smooth, moving 2-camera latents (8 channels on 4×6) with every label, in the mode=encode layout."""
    rig = build_rig(["front", "front_left"], 32, 48)
    for split, seed in (("train", 0), ("val", 1)):
        rng = np.random.default_rng(seed)
        for i in range(clips):
            base = 0.3 * rng.normal(size=(2, 1, 8, 4, 6)).astype(np.float32)
            drift = np.linspace(0, 1, steps, dtype=np.float32)[None, :, None, None, None]
            frames = steps * 4
            write_latent_clip(root / split, LatentClip(
                clip_id=f"clip_{i}", mean=base + drift, logvar=np.full((2, steps, 8, 4, 6), -6, np.float32),
                temporal_downsampling=4, fps=12.5, image_size=(32, 48), timestamps=np.arange(frames) / 12.5,
                cameras=[CameraSpec(c.name, c.intrinsics, c.extrinsics, c.width, c.height) for c in rig],
                meta={"weather": "rain", "time_of_day": "night"}, actions=np.ones((frames, 2), np.float32) * [10, 0.01],
                text=["It is night."] * frames,
                agents=[AgentBoxes([[12.0, 0.5, 0.8]], [[4.5, 1.8, 1.6]], [0.0], [0], [1]) for _ in range(frames)]))


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("latents")
    write_cache(root)
    return root


def datamodule(cache: Path, steps: int = 3) -> LatentCacheDataModule:
    dm = LatentCacheDataModule(str(cache), steps=steps, metadata_fields=list(META), batch_size=3)
    dm.setup("fit")
    return dm


def test_windows_carry_per_step_conditions(cache: Path) -> None:
    batch = next(iter(datamodule(cache).val_dataloader()))
    assert batch["mean"].shape == (3, 2, 3, 8, 4, 6)
    assert batch["actions"].shape == (3, 3, 2) and torch.allclose(batch["actions"][..., 0], torch.tensor(10.0))
    torch.testing.assert_close(batch["timestamps"][0], torch.tensor([0.0, 0.32, 0.64]))
    assert batch["agents_centre"].shape == (3, 3, 1, 3) and batch["intrinsics"].shape == (3, 2, 3, 3)
    assert batch["metadata"]["weather"].tolist() == [2, 2, 2] and batch["text"][0] == "It is night."
    cond = batch_conditions(batch)
    assert cond.active("agents") and cond.active("metadata") and cond.image_size == (32, 48)


def make_module(net=None, **kw) -> LatentWorldModelModule:
    torch.manual_seed(0)
    net = net or functools.partial(LatentWorldModel, latent_channels=8, dim=48, depth=2, heads=4, metadata_fields=META)
    return LatentWorldModelModule(net=net, optim=functools.partial(torch.optim.AdamW, lr=2e-3), **kw)


def fixed_tau_loss(module: LatentWorldModelModule, batch: dict, tau: float = 0.5) -> float:
    """Velocity MSE of every step at one τ and a fixed noise draw (deterministic, unlike the training loss)."""
    x = module.latents(batch, sample=False)
    noise = torch.randn(x.shape, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        return float(module.flow_loss(x, module.task_taus(len(x), x.shape[2], torch.full((len(x),), tau)),
                                      batch_conditions(batch), noise))


def test_flow_matching_learns_the_cached_latents(cache: Path) -> None:
    """Overfitting three clips: the velocity error at τ = 0.5 (fixed noise) falls at least 2.5× in 150 steps."""
    module = make_module()
    dm = datamodule(cache)
    batch = collate_latent_windows([LatentWindows(find_latent_clips(cache / "train"), 3, MetadataEncoder(list(META)),
                                                  random_window=False)[i] for i in range(3)])
    module.configure_model()
    before = fixed_tau_loss(module, batch)
    trainer = L.Trainer(max_steps=150, accelerator="cpu", logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0)
    trainer.fit(module, dm)
    after = fixed_tau_loss(module.eval(), batch)
    assert after < before / 2.5, f"velocity error at τ = 0.5: {before:.3f} → {after:.3f}"


def test_context_steps_are_clean_and_excluded_from_the_loss(cache: Path) -> None:
    module = make_module()
    taus = module.task_taus(2, 4, torch.tensor([0.3, 0.6]), context=torch.tensor([0, 2]))
    torch.testing.assert_close(taus, torch.tensor([[0.3] * 4, [1.0, 1.0, 0.6, 0.6]]))
    batch = next(iter(datamodule(cache).val_dataloader()))
    x = module.latents(batch, sample=False)
    cond = batch_conditions(batch)
    seen = {}
    module.model.register_forward_pre_hook(lambda m, args: seen.update(x_tau=args[0]))
    noise = torch.randn_like(x)
    loss = module.flow_loss(x, module.task_taus(3, 3, torch.full((3,), 0.5), torch.tensor([2, 2, 2])), cond, noise)
    torch.testing.assert_close(seen["x_tau"][:, :, :2], x[:, :, :2])  # context steps enter clean
    torch.testing.assert_close(seen["x_tau"][:, :, 2], 0.5 * x[:, :, 2] + 0.5 * noise[:, :, 2])
    # an untrained model predicts v = 0: the loss is the mean of (x − ε)² over the generated step only
    torch.testing.assert_close(loss, (x[:, :, 2] - noise[:, :, 2]).pow(2).mean())


def test_agent_loss_weight_weighs_the_cells_under_the_boxes(cache: Path) -> None:
    """λ = 9: the cells under the car ahead (in the front camera only) weigh 10× the rest, the mean weight is 1, and
    the weighted loss is the weighted mean of the same squared errors; λ = 0 leaves the report's plain mean."""
    batch = next(iter(datamodule(cache).val_dataloader()))
    assert make_module().position_weights(torch.zeros(3, 2, 3, 8, 4, 6), batch_conditions(batch)) is None
    module = make_module(agent_loss_weight=9.0)
    x = module.latents(batch, sample=False)
    cond = batch_conditions(batch)
    weights = module.position_weights(x, cond)
    assert weights.shape == (3, 2, 3, 1, 4, 6)
    torch.testing.assert_close(weights.mean(), torch.tensor(1.0))
    front, side = weights[:, 0], weights[:, 1]
    assert torch.allclose(side, side.amin()), "the car 12 m ahead is in no cell of the left camera"
    assert front.amax() / front.amin() > 5 and float((front > front.amin()).float().mean()) < 0.5
    noise = torch.randn_like(x)
    taus = module.task_taus(3, 3, torch.full((3,), 0.5))
    weighted = module.flow_loss(x, taus, cond, noise, weights)  # an untrained net predicts v = 0
    torch.testing.assert_close(weighted, ((x - noise).pow(2) * weights).mean())
    with pytest.raises(ValueError, match="agent boxes"):
        module.position_weights(x, batch_conditions({k: v for k, v in batch.items() if not k.startswith("agents")}))
    with pytest.raises(ValueError, match="agent_loss_weight"):
        make_module(agent_loss_weight=-1.0)


def test_context_draws_cover_scratch_and_prediction() -> None:
    module = make_module(context_prob=0.5)
    torch.manual_seed(0)
    k = module.draw_context(2000, 4, torch.device("cpu"))
    assert 0.4 < (k == 0).float().mean() < 0.6 and set(k.tolist()) == {0, 1, 2, 3}


def pretrain(module: LatentWorldModelModule, cache: Path, path: Path) -> None:
    """Three steps of `module`, saved as a training checkpoint at `path`."""
    trainer = L.Trainer(max_steps=3, accelerator="cpu", logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0)
    trainer.fit(module, datamodule(cache))
    trainer.save_checkpoint(path)


def at_first_step(module: LatentWorldModelModule, cache: Path, read: Callable[[LatentWorldModelModule], Any]) -> Any:
    """read(module) at the start of the first training batch of a one-step fit (after init_from is applied)."""
    seen = {}

    class Probe(L.Callback):
        def on_train_batch_start(self, trainer, module, batch, batch_idx) -> None:
            seen.setdefault("first", read(module))

    L.Trainer(max_steps=1, accelerator="cpu", logger=False, enable_checkpointing=False, enable_progress_bar=False,
              enable_model_summary=False, limit_val_batches=0, callbacks=[Probe()]).fit(module, datamodule(cache))
    return seen["first"]


def test_init_from_carries_a_learned_text_encoder(cache: Path, tmp_path: Path) -> None:
    """A trainable text encoder is part of what the net learned to read: init_from starts it from the checkpoint too,
    so the fine-tune's first step sees the same caption embeddings as the pretrained run's last."""
    text = functools.partial(LearnedTextEncoder, dim=16, tokens=4)
    net = functools.partial(LatentWorldModel, latent_channels=8, dim=48, depth=2, heads=4, metadata_fields=META,
                            text_dim=16)
    pretrained = make_module(net=net, text_encoder=text)
    pretrain(pretrained, cache, tmp_path / "pretrained.ckpt")
    torch.manual_seed(1)
    tuned = make_module(net=net, text_encoder=text, init_from=str(tmp_path / "pretrained.ckpt"))
    first = at_first_step(tuned, cache, lambda m: m.text_encoder.embedding.weight.detach().clone())
    torch.testing.assert_close(first, pretrained.text_encoder.embedding.weight)


def test_init_from_starts_a_fresh_fit_from_another_runs_net(cache: Path, tmp_path: Path) -> None:
    """model.init_from (fine-tuning): a fresh fit starts from the checkpoint's net weights, not its own init; a
    checkpoint of another architecture is refused naming the setting."""
    pretrained = make_module()
    pretrain(pretrained, cache, tmp_path / "pretrained.ckpt")
    tuned = make_module(init_from=str(tmp_path / "pretrained.ckpt"))
    torch.manual_seed(1)  # a different own init: only init_from can make the weights equal
    first = at_first_step(tuned, cache, lambda m: {k: v.detach().clone() for k, v in m.model.state_dict().items()})
    for name, value in pretrained.model.state_dict().items():
        torch.testing.assert_close(first[name], value)
    other = LatentWorldModelModule(net=functools.partial(LatentWorldModel, latent_channels=8, dim=32, depth=1, heads=4,
                                                         metadata_fields=META),
                                   optim=functools.partial(torch.optim.AdamW, lr=1e-3),
                                   init_from=str(tmp_path / "pretrained.ckpt"))
    with pytest.raises(ValueError, match="model.init_from=.*does not fit model.net"):
        L.Trainer(max_steps=1, accelerator="cpu", logger=False, enable_checkpointing=False, enable_progress_bar=False,
                  enable_model_summary=False, limit_val_batches=0).fit(other, datamodule(cache))


def test_init_from_a_weights_folder(cache: Path, tmp_path: Path) -> None:
    """model.init_from may name a weights folder (e.g. the shipped gaia2): fine-tuning the shipped world model needs
    no training checkpoint. Its `latent_world_model` tensors start the fit; another component or a missing path is
    refused naming the setting."""
    import yaml
    from safetensors.torch import save_file

    pretrained = make_module()
    pretrain(pretrained, cache, tmp_path / "pretrained.ckpt")
    folder = tmp_path / "weights"
    folder.mkdir()
    save_file({f"net.{k}": v.contiguous() for k, v in pretrained.model.state_dict().items()},
              str(folder / "latent_world_model.safetensors"))
    config = {"format": 1, "component": "latent_world_model", "dtype": "float32",
              "nets": {"net": {"_target_": "gaia_app.models.gaia2.latent_world_model.LatentWorldModel"}}}
    (folder / "latent_world_model.yaml").write_text(yaml.safe_dump(config))
    torch.manual_seed(1)
    tuned = make_module(init_from=str(folder))
    first = at_first_step(tuned, cache, lambda m: {k: v.detach().clone() for k, v in m.model.state_dict().items()})
    for name, value in pretrained.model.state_dict().items():
        torch.testing.assert_close(first[name], value)
    (folder / "latent_world_model.yaml").write_text(yaml.safe_dump({**config, "component": "video_tokenizer"}))
    with pytest.raises(ValueError, match="latent_world_model.yaml is not a latent_world_model component"):
        at_first_step(make_module(init_from=str(folder)), cache, lambda m: None)
    with pytest.raises(FileNotFoundError, match="neither a file nor a weights folder"):
        at_first_step(make_module(init_from=str(tmp_path / "nowhere")), cache, lambda m: None)
