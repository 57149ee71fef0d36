"""Distributed training on CPU (issue 8, ECOSYSTEM.md §2): Lightning's DDP and FSDP2 on 2 gloo processes through
train.py, strategy configs that need GPUs constructed, a raw DeepSpeed ZeRO-2 step, sharded checkpoints loading on
one CPU, one run dir per run, activation checkpointing on every model."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf, open_dict
from torch import nn

from gaia_app.lit.checkpoint import load_module
from gaia_app.lit.strategies import FSDP2Strategy, block_types_of, build_strategy, enable_activation_checkpointing
from gaia_app.models.gaia1.tokenizer import ImageTokenizer
from gaia_app.tasks.train import build
from gaia_app.utils.resolvers import launch_id
from tests.conftest import DEEPSPEED_ONE_PROCESS, ROOT, compose_config

NETS = ["gaia1_tokenizer_tiny", "gaia1_world_model_tiny", "gaia1_video_decoder_tiny", "gaia2_video_tokenizer_tiny",
        "gaia2_world_model_tiny"]


@pytest.fixture(scope="module")
def token_cache(tmp_path_factory) -> Path:
    """One 60-step segment of 3×4 tokens (vocabulary 16) drifting one code per step, with actions."""
    root = tmp_path_factory.mktemp("tokens")
    tokens = (np.random.default_rng(0).integers(0, 16, size=12)[None] + np.arange(60)[:, None]) % 16
    np.save(root / "seg.npy", tokens.reshape(60, 3, 4).astype(np.int16))
    np.save(root / "seg.actions.npy", np.random.default_rng(1).normal(size=(60, 2)).astype(np.float32))
    return root


def world_model_args(cache: Path, log_dir: Path) -> list[str]:
    return ["experiment=gaia1/world_model_tiny", "trainer.accelerator=cpu", "trainer.devices=2", "trainer.max_steps=3",
            "trainer.val_check_interval=3", "trainer.limit_val_batches=1", "+trainer.num_sanity_val_steps=0",
            f"data.path={cache}", "data.frame_stride=1", "data.batch_size=2", "model.net.vocab_size=16",
            "model.net.image_tokens=12", "model.net.dim=32", "model.net.depth=2", "model.net.heads=2",
            "model.net.kv_heads=1", "extras.print_config=false", f"paths.log_dir={log_dir}",
            "callbacks.rerun_media=null"]


def run_train(args: list[str], **env: str) -> subprocess.CompletedProcess:
    """train.py in a fresh interpreter (Lightning re-launches it for rank 1) with one thread per rank."""
    environment = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT), **env}
    done = subprocess.run([sys.executable, "train.py", *args], cwd=ROOT, capture_output=True, text=True,
                          env=environment, timeout=420)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-5000:]
    return done


def only_run_dir(log_dir: Path) -> Path:
    runs = [p for p in (log_dir / "gaia1_world_model_tiny").iterdir() if p.is_dir()]
    assert len(runs) == 1, f"one run dir per run, not per rank: {runs}"
    return runs[0]


def logits_of(module) -> torch.Tensor:
    """Next-token logits of the tiny world model for a fixed (2, 4, 12) token batch."""
    tokens = torch.arange(2 * 4 * 12).remainder(16).reshape(2, 4, 12)
    with torch.no_grad():
        return module.world_model(tokens, module.conditions({"tokens": tokens, "actions": torch.zeros(2, 4, 2)}))


@pytest.mark.slow
def test_ddp_two_cpu_processes_share_one_run_dir(token_cache: Path, tmp_path: Path) -> None:
    done = run_train([*world_model_args(token_cache, tmp_path), "trainer=ddp", "trainer.precision=32-true"])
    log = done.stdout + done.stderr
    assert "MEMBER: 2/2" in log, "rank 1 did not join"
    run = only_run_dir(tmp_path)
    assert (run / "checkpoints" / "last.ckpt").is_file()
    assert [p.name for p in run.rglob("*.rrd")] == ["run.rrd"], "only rank 0 writes the recording"
    assert (run / "train_ddp_process_1.log").is_file(), "rank 1 logs into the parent's run dir"
    module = load_module(run / "checkpoints" / "last.ckpt")
    assert torch.isfinite(logits_of(module)).all()


@pytest.mark.slow
def test_fsdp2_shards_on_two_cpu_processes_and_loads_on_one(token_cache: Path, tmp_path: Path) -> None:
    done = run_train([*world_model_args(token_cache, tmp_path), "trainer=fsdp2",
                      "trainer.strategy.activation_checkpointing=true"])
    assert "MEMBER: 2/2" in done.stdout + done.stderr
    ckpt = only_run_dir(tmp_path) / "checkpoints" / "last.ckpt"
    shards = sorted(ckpt.glob("*.distcp"))
    assert ckpt.is_dir() and len(shards) == 2, f"one shard per rank expected in {ckpt}: {list(ckpt.iterdir())}"
    sizes = [p.stat().st_size for p in shards]
    assert min(sizes) > 0.3 * max(sizes), f"shards should split the weights: {sizes}"
    module = load_module(ckpt)  # one CPU process, no process group
    # every parameter got gradients, the root unit's included, except the text path: this cache has no captions
    assert stale_parameters(ckpt, module, tmp_path) == ["net.conditioner.text_proj.weight",
                                                        "net.conditioner.text_proj.bias",
                                                        "text_encoder.embedding.weight"]
    trained = dict(module.net.named_parameters())
    fresh = dict(instantiate(compose_config("train", world_model_args(Path("x"), tmp_path), tmp_path).model)
                 .net_factory().named_parameters())
    assert trained.keys() == fresh.keys(), "sharding must not rename parameters"
    assert torch.isfinite(logits_of(module)).all()
    # generation from the gathered weights: one new frame after two context frames, KV-cached
    from gaia_app.diffusion.ar_sampling import AutoregressiveSampler, TokenPicker

    context = torch.arange(24).remainder(16).reshape(1, 2, 12)
    cond = module.world_model.conditioner(1, 3, force_drop={"text": True, "actions": True})
    rollout = AutoregressiveSampler(TokenPicker("argmax"))(module.world_model, context, cond, frames=1)
    assert rollout.shape == (1, 3, 12) and torch.equal(rollout[:, :2], context)


def test_fsdp_sharded_checkpoint_loads_on_one_cpu(token_cache: Path, tmp_path: Path) -> None:
    """`trainer=fsdp` (Lightning's FSDPStrategy, CUDA only) keeps the weights under "model" in its shards, not under
    "state_dict" as fsdp2 does; loading such a checkpoint failed (seen on an H200). The layout is rebuilt here as that
    strategy writes it, from a one-process CPU run."""
    import torch.distributed.checkpoint as dcp

    from gaia_app.tasks.train import train

    one_process = [arg for arg in world_model_args(token_cache, tmp_path) if not arg.startswith("trainer.devices")]
    train(compose_config("train", [*one_process, "trainer.devices=1"], tmp_path / "run"))  # in this process
    single_file = tmp_path / "run" / "checkpoints" / "last.ckpt"
    checkpoint = torch.load(single_file, map_location="cpu", weights_only=False)
    sharded = tmp_path / "fsdp_last.ckpt"
    dcp.save({"model": checkpoint.pop("state_dict")}, checkpoint_id=sharded, no_dist=True)
    torch.save(checkpoint, sharded / "meta.pt")
    assert torch.equal(logits_of(load_module(sharded)), logits_of(load_module(single_file)))
    dcp.save({"optimizer_0": {"step": torch.tensor(1.0)}}, checkpoint_id=tmp_path / "empty", no_dist=True)
    torch.save(checkpoint, tmp_path / "empty" / "meta.pt")
    with pytest.raises(KeyError, match="'state_dict' \\(fsdp2\\) or 'model' \\(fsdp\\)"):
        load_module(tmp_path / "empty")


def test_fsdp_clips_gradients_by_their_global_norm(tmp_path: Path) -> None:
    """`trainer.gradient_clip_val` under `trainer=fsdp`: Lightning's FSDP precision plugin refuses norm clipping, which
    stopped the world model's first step on an H200; GaiaModule routes it to FSDP's own clip_grad_norm_. FSDP1 runs on
    CPU in one gloo process here (Lightning itself allows it on CUDA only)."""
    from functools import partial
    from types import SimpleNamespace

    import torch.distributed as dist
    from lightning.pytorch.plugins.precision import FSDPPrecision
    from torch.distributed.fsdp import FullyShardedDataParallel

    from gaia_app.lit.base import GaiaModule

    module = GaiaModule(net=lambda: nn.Sequential(nn.Linear(4, 8), nn.Linear(8, 1)),
                        optim=partial(torch.optim.SGD, lr=0.1))
    module.configure_model()
    dist.init_process_group("gloo", init_method=f"file://{tmp_path / 'rendezvous'}", rank=0, world_size=1)
    try:
        wrapped = FullyShardedDataParallel(module, device_id=torch.device("cpu"))
        module._trainer = SimpleNamespace(model=wrapped, precision_plugin=FSDPPrecision("32-true"),
                                          gradient_clip_val=0.5, gradient_clip_algorithm=None)
        wrapped.net(torch.randn(16, 4)).square().sum().mul(1e3).backward()

        def norm() -> torch.Tensor:
            return torch.linalg.vector_norm(torch.stack([p.grad.norm() for p in wrapped.parameters()]))

        assert norm() > 10
        module.configure_gradient_clipping(torch.optim.SGD(wrapped.parameters(), lr=0.1), gradient_clip_val=0.5)
        assert norm() == pytest.approx(0.5, rel=1e-4)
    finally:
        dist.destroy_process_group()


def stale_parameters(ckpt: Path, module, tmp_path: Path) -> list[str]:
    """Trainable parameters whose AdamW moments in the sharded checkpoint are missing or zero (no gradient)."""
    from torch.distributed.checkpoint.format_utils import dcp_to_torch_save

    dcp_to_torch_save(ckpt, tmp_path / "gathered.pt")
    state = torch.load(tmp_path / "gathered.pt", weights_only=False)["optimizer_0"]["state"]
    return [name for name, p in module.named_parameters()
            if p.requires_grad and (name not in state or not state[name]["exp_avg"].abs().sum() > 0)]


@pytest.mark.slow
def test_deepspeed_zero2_step_on_cpu(tmp_path: Path) -> None:
    """A raw `deepspeed.initialize` ZeRO-2 run of the tiny world model (Lightning's DeepSpeedStrategy is CUDA-only)."""
    pytest.importorskip("deepspeed")
    script = tmp_path / "zero2.py"
    script.write_text(DEEPSPEED_ONE_PROCESS + ZERO2_SCRIPT)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT), "MASTER_ADDR": "127.0.0.1",
           "MASTER_PORT": "29561", "RANK": "0", "LOCAL_RANK": "0", "WORLD_SIZE": "1", "DS_ACCELERATOR": "cpu"}
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    first, last = (float(x) for x in done.stdout.strip().splitlines()[-1].split())
    assert last < 0.7 * first, f"ZeRO-2 steps should overfit one batch: {first} → {last}"


ZERO2_SCRIPT = """
import deepspeed, torch
import torch.nn.functional as F
from gaia_app.models.gaia1.world_model import WorldModel
torch.manual_seed(0)
deepspeed.init_distributed(dist_backend="gloo")
net = WorldModel(16, 32, 2, 2, kv_heads=1, frames=4, image_tokens=12)
config = {"train_micro_batch_size_per_gpu": 2, "zero_optimization": {"stage": 2}, "gradient_clipping": 1.0}
engine, _, _, _ = deepspeed.initialize(model=net, optimizer=torch.optim.AdamW(net.parameters(), lr=3e-3), config=config)
tokens = torch.arange(2 * 4 * 12).remainder(16).reshape(2, 4, 12)
losses = []
for _ in range(25):
    logits = engine(tokens, net.conditioner(2, 4, None, torch.zeros(2, 4, 2)))
    loss = F.cross_entropy(logits.reshape(-1, 16), tokens.reshape(-1))
    engine.backward(loss)
    engine.step()
    losses.append(loss.item())
assert engine.zero_optimization_stage() == 2
print(losses[0], losses[-1])
"""


@pytest.mark.parametrize("name", ["ddp", "fsdp", "fsdp2", "deepspeed_zero2", "deepspeed_zero3_offload"])
def test_strategy_configs_construct_with_the_models_blocks(name: str, tmp_path: Path) -> None:
    if name.startswith("deepspeed"):
        pytest.importorskip("deepspeed")
    cfg = compose_config("train", ["experiment=gaia1/video_decoder_tiny", f"trainer={name}"], tmp_path)
    module = instantiate(cfg.model)
    strategy = build_strategy(cfg.trainer.strategy, module)
    assert type(strategy).__name__ == cfg.trainer.strategy._target_.rsplit(".", 1)[-1]
    if name == "fsdp":
        from gaia_app.models.gaia1.video_decoder import SpaceTimeBlock

        assert strategy.kwargs["auto_wrap_policy"]._module_classes == {SpaceTimeBlock}
        assert strategy._activation_checkpointing_kwargs["auto_wrap_policy"]._module_classes == {SpaceTimeBlock}
    if name == "fsdp2":
        assert isinstance(strategy, FSDP2Strategy) and strategy.param_dtype == torch.bfloat16


def test_strategy_overrides_without_a_strategy_are_an_error() -> None:
    with pytest.raises(ValueError, match="names no _target_"):
        build_strategy(OmegaConf.create({"find_unused_parameters": True}), nn.Linear(1, 1))


@pytest.mark.parametrize("net", NETS)
def test_every_model_names_its_blocks_and_can_checkpoint_them(net: str, tmp_path: Path) -> None:
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(ROOT / "conf" / "model" / "net"), version_base="1.3"):
        net_cfg = compose(config_name=net)
    with open_dict(net_cfg):
        if "text_dim" in net_cfg:
            net_cfg.text_dim = 16
    factory = instantiate(net_cfg)
    model = factory()
    types = block_types_of(type("Module", (), {"net_factory": factory})())
    assert sum(isinstance(m, types) for m in model.modules()) >= 2, f"{net}: repeated blocks {types} not found"
    assert enable_activation_checkpointing(model) >= 1


def test_tokenizer_checkpointing_gives_the_same_gradients() -> None:
    torch.manual_seed(0)
    plain = ImageTokenizer(channels=8, channel_mults=(1, 2), blocks_per_stage=1, latent_dim=8, codebook_size=16,
                           code_dim=4)
    recomputed = ImageTokenizer(channels=8, channel_mults=(1, 2), blocks_per_stage=1, latent_dim=8, codebook_size=16,
                                code_dim=4, checkpointing=True)
    recomputed.load_state_dict(plain.state_dict())
    image = torch.randn(2, 3, 16, 16)
    grads = []
    for net in (plain, recomputed):
        net(image).reconstruction.square().mean().backward()
        grads.append(net.encoder.stem.weight.grad.clone())
    torch.testing.assert_close(grads[0], grads[1])


def test_sweep_with_a_relaunching_strategy_is_refused(tmp_path: Path) -> None:
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    cfg = compose_config("train", ["experiment=gaia1/video_decoder_tiny", "trainer=ddp", "trainer.accelerator=cpu",
                                   "trainer.precision=32-true", "hydra.mode=MULTIRUN"], tmp_path)
    assert HydraConfig.get().mode == RunMode.MULTIRUN
    with pytest.raises(ValueError, match="re-runs the whole sweep"):
        build(cfg)


def test_launch_id_is_shared_by_the_ranks_of_one_launch(monkeypatch) -> None:
    for var in ("SLURM_JOB_ID", "SLURM_STEP_ID", "TORCHELASTIC_RUN_ID"):
        monkeypatch.delenv(var, raising=False)
    assert launch_id("2026-11-24_10-00-00") == "2026-11-24_10-00-00"
    monkeypatch.setenv("TORCHELASTIC_RUN_ID", "none")  # torchrun without a rendezvous id
    assert launch_id("stamp") == "stamp"
    monkeypatch.setenv("TORCHELASTIC_RUN_ID", "abc123")
    assert launch_id("stamp") == "torchrun_abc123"
    monkeypatch.setenv("SLURM_JOB_ID", "777")
    assert launch_id("stamp") == "torchrun_abc123", "an allocation without srun is not a launch"
    monkeypatch.setenv("SLURM_STEP_ID", "3")
    assert launch_id("stamp") == "slurm777.3"


def test_compile_option_compiles_the_net_in_place(token_cache: Path, tmp_path: Path) -> None:
    from gaia_app.tasks.train import train

    args = [a for a in world_model_args(token_cache, tmp_path) if not a.startswith("trainer.devices")]
    cfg = compose_config("train", [*args, "trainer.max_steps=2", "logger=csv", "compile.enabled=true",
                                   "compile.backend=eager"], tmp_path)
    out = train(cfg)
    net = out["model"].net
    assert out["trainer"].global_step == 2 and net._compiled_call_impl is not None
    names = set(torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=False)["state_dict"])
    assert "net.conditioner.action_weight" in names and not any("_orig_mod" in n for n in names)
