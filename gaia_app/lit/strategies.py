"""Distributed training through Lightning's own strategies, chosen by `trainer=` config (GAIA-1 §4).

No home-made distribution code: DDP, FSDP (FSDP1, GPU), FSDP2 through `ModelParallelStrategy` and DeepSpeed
are Lightning's. What this module adds is the one thing they need from the models: *which* modules are the
repeated blocks to wrap, shard and checkpoint. Every net names them in its `block_types` class attribute, so a
strategy config says `auto_wrap_policy: blocks` and `build_strategy` puts the model's block classes there.

    trainer=ddp             DDPStrategy (gloo on CPU, NCCL on GPU)
    trainer=fsdp            StagedFSDPStrategy: wrap + activation checkpointing of the blocks, sharded checkpoints
    trainer=fsdp2           FSDP2Strategy below: fully_shard per block, then the module (runs on CPU/gloo too)
    trainer=deepspeed_zero2 / deepspeed_zero3_offload   StagedDeepSpeedStrategy (CUDA only in Lightning)

The three sharding strategies write a checkpoint as a folder, every rank its part, over the previous one in place: a
crash in the middle of a save would leave a folder of mixed steps that no resume can read. Here they write into
`<name>.partial` and swap it in when every rank is done (`StagedSave`, gaia_app/lit/staged_checkpoints.py).
"""

from __future__ import annotations

from typing import Any

import torch
from hydra.utils import instantiate
from lightning.pytorch.strategies import DeepSpeedStrategy, FSDPStrategy, ModelParallelStrategy, Strategy
from omegaconf import DictConfig, OmegaConf
from torch import nn

from gaia_app.lit.staged_checkpoints import StagedSave

BLOCKS = "blocks"
POLICY_KEYS = ("auto_wrap_policy", "activation_checkpointing_policy")


def block_types_of(module: nn.Module) -> tuple[type[nn.Module], ...]:
    """The repeated block classes of a GaiaModule's net, read from the class (the net need not be built yet)."""
    factory = getattr(module, "net_factory", None)
    net_class = getattr(factory, "func", factory) if factory is not None else type(module)
    types = getattr(net_class, "block_types", None)
    if not types:
        raise ValueError(f"{getattr(net_class, '__name__', net_class)} declares no `block_types`; sharding and "
                         "activation-checkpointing policies need the classes of its repeated blocks")
    return tuple(types)


def build_strategy(node: DictConfig | str | None, module: nn.Module) -> Strategy | str:
    """`cfg.trainer.strategy` → what `Trainer(strategy=...)` takes.

    A string ("auto", "ddp") passes through; a `_target_` node is instantiated, with every policy entry that
    says `blocks` replaced by the set of the model's block classes.
    """
    if node is None:
        return "auto"
    if isinstance(node, str):
        return node
    spec: dict[str, Any] = OmegaConf.to_container(node, resolve=True)  # type: ignore[assignment]
    if "_target_" not in spec:
        raise ValueError(f"trainer.strategy={spec} names no _target_: it overrides keys of a strategy that the chosen "
                         "trainer= config does not define (pick trainer=ddp / fsdp / fsdp2 / deepspeed_zero2 ...)")
    policies = {key: set(block_types_of(module)) for key in POLICY_KEYS if spec.get(key) == BLOCKS}
    for key in policies:
        spec.pop(key)
    return instantiate(spec, **policies)


def enable_activation_checkpointing(net: nn.Module) -> int:
    """Switch on every `checkpointing` flag in `net` (the nets recompute their blocks in backward); returns how many.

    The nets' own flags are used instead of `checkpoint_wrapper` so parameter names, and with them checkpoints,
    stay the same whichever strategy trained the model.
    """
    switched = 0
    for sub in net.modules():
        if isinstance(getattr(sub, "checkpointing", None), bool):
            sub.checkpointing = True
            switched += 1
    if not switched:
        raise ValueError(f"{type(net).__name__} has no `checkpointing` flag to switch on")
    return switched


def dtype_of(name: str | None) -> torch.dtype | None:
    """'bfloat16' / 'float32' / None → the torch dtype (None keeps the parameters' own)."""
    if name is None:
        return None
    dtype = getattr(torch, name, None)
    if not isinstance(dtype, torch.dtype):
        raise ValueError(f"unknown dtype {name!r}; expected a torch dtype name such as 'bfloat16' or 'float32'")
    return dtype


def fill_missing_optimizer_state(optimizer: torch.optim.Optimizer) -> int:
    """Give every trained parameter that has no optimizer state yet (it never had a gradient: a text encoder on
    data without captions, a dropped condition) the state the optimizer would create lazily at its first gradient,
    so that a checkpoint holds an entry for each (torch.distributed.checkpoint initialises a fresh optimizer's state
    for every parameter before loading into it). Built by one step with zero gradients at learning rate 0 on those
    parameters alone, then their step counters reset to 0, so a later first update is the one an optimizer without
    the state would make. No weight moves: the other parameters take no step (decoupled weight decay, as AdamW's,
    acts only through the step; L2-in-the-gradient optimizers see a zero gradient), and gradients and learning rates
    are restored. Runs outside inference mode (a checkpoint saved from a validation hook would otherwise create
    inference tensors that a later update cannot modify). Returns how many parameters got a state."""
    params = [p for group in optimizer.param_groups for p in group["params"]]
    missing = {id(p) for p in params if p.requires_grad and not optimizer.state.get(p)}
    if not missing:
        return 0
    grads, rates = [p.grad for p in params], [group["lr"] for group in optimizer.param_groups]
    with torch.inference_mode(False), torch.no_grad():
        try:
            for p in params:
                p.grad = torch.zeros_like(p) if id(p) in missing else None
            for group in optimizer.param_groups:
                group["lr"] = torch.zeros_like(group["lr"]) if isinstance(group["lr"], torch.Tensor) else 0.0
            optimizer.step()
        finally:
            for p, grad in zip(params, grads):
                p.grad = grad
            for group, rate in zip(optimizer.param_groups, rates):
                group["lr"] = rate
        for p in params:
            step = optimizer.state[p].get("step") if id(p) in missing else None
            if isinstance(step, torch.Tensor):
                step.zero_()
            elif step is not None:
                optimizer.state[p]["step"] = 0
    return len(missing)


class StagedFSDPStrategy(StagedSave, FSDPStrategy):
    """Lightning's FSDPStrategy whose checkpoints are staged and swapped in whole (StagedSave)."""


class StagedDeepSpeedStrategy(StagedSave, DeepSpeedStrategy):
    """Lightning's DeepSpeedStrategy whose checkpoint folders are staged and swapped in whole (StagedSave)."""


class FSDP2Strategy(StagedSave, ModelParallelStrategy):
    """FSDP2 (`fully_shard`) as Lightning's `ModelParallelStrategy`, sharding a GaiaModule without model code.

    After `configure_model()` built the net, each block of the net's `block_types` is sharded on the data-parallel
    mesh, then the whole LightningModule (embeddings, heads, EMA copies): every trained parameter is a DTensor
    whose gradients are reduce-scattered across ranks. Runs on CPU with gloo, which is how the tests run it.

    Args:
        activation_checkpointing: switch on the nets' own checkpointing of their blocks.
        param_dtype, reduce_dtype: FSDP2 mixed precision (e.g. 'bfloat16', 'float32'); None keeps fp32.
        reshard_after_forward: free gathered parameters after each block's forward (ZeRO-3 style, less memory).
        data_parallel_size: ranks sharding the model; "all" (default) is every process of every node.
        **kwargs: `ModelParallelStrategy` arguments (tensor_parallel_size, save_distributed_checkpoint, timeout…).
    """

    def __init__(self, activation_checkpointing: bool = False, param_dtype: str | None = None,
                 reduce_dtype: str | None = None, reshard_after_forward: bool = True,
                 data_parallel_size: int | str = "all", tensor_parallel_size: int | str = 1, **kwargs: Any):
        super().__init__(data_parallel_size=data_parallel_size, tensor_parallel_size=tensor_parallel_size, **kwargs)
        self.activation_checkpointing = activation_checkpointing
        self.param_dtype, self.reduce_dtype = dtype_of(param_dtype), dtype_of(reduce_dtype)
        self.reshard_after_forward = reshard_after_forward

    def setup_environment(self) -> None:
        if self._data_parallel_size == "all":
            self._data_parallel_size = self.num_nodes * self.num_processes
        super().setup_environment()

    def setup(self, trainer: Any) -> None:
        self.shard(self.lightning_module)
        super().setup(trainer)

    # FSDP2 gathers a unit's parameters in its forward pre-hook, and the modules call their nets' parts directly
    # (conditioner, encode, decode) from their step methods: each step is routed through the root module's
    # __call__, the way Lightning routes steps through DDP / FSDP wrappers, so the root unit is gathered for the
    # whole step and its gradients are reduce-scattered after backward.
    def training_step(self, *args: Any, **kwargs: Any) -> Any:
        return self.redirected("training_step", self.precision_plugin.train_step_context(), *args, **kwargs)

    def validation_step(self, *args: Any, **kwargs: Any) -> Any:
        return self.redirected("validation_step", self.precision_plugin.val_step_context(), *args, **kwargs)

    def test_step(self, *args: Any, **kwargs: Any) -> Any:
        return self.redirected("test_step", self.precision_plugin.test_step_context(), *args, **kwargs)

    def predict_step(self, *args: Any, **kwargs: Any) -> Any:
        return self.redirected("predict_step", self.precision_plugin.predict_step_context(), *args, **kwargs)

    def redirected(self, step: str, context: Any, *args: Any, **kwargs: Any) -> Any:
        with context:
            return self._forward_redirection(self.model, self.lightning_module, step, *args, **kwargs)

    def optimizer_state(self, optimizer: Any) -> dict[str, Any]:
        """The optimizer's state for the checkpoint, with an entry for every trained parameter (see
        `fill_missing_optimizer_state`): resuming builds the live optimizer's state for all of them and loads
        each entry it builds from the checkpoint, so one missing there stops the resume."""
        fill_missing_optimizer_state(getattr(optimizer, "_optimizer", optimizer))
        return super().optimizer_state(optimizer)

    def shard(self, module: nn.Module) -> None:
        """fully_shard each repeated block of `module.net` (innermost first), then `module` itself. Idempotent."""
        from torch.distributed.fsdp import FSDPModule, MixedPrecisionPolicy, fully_shard

        if isinstance(module, FSDPModule):
            return
        net = getattr(module, "net", None)
        if net is None:
            raise ValueError(f"{type(module).__name__} has no built `net`; FSDP2Strategy shards GaiaModules after "
                             "configure_model()")
        if self.activation_checkpointing:
            enable_activation_checkpointing(net)
        options = {"mesh": self.device_mesh["data_parallel"], "reshard_after_forward": self.reshard_after_forward,
                   "mp_policy": MixedPrecisionPolicy(param_dtype=self.param_dtype, reduce_dtype=self.reduce_dtype)}
        types = block_types_of(module)
        # children before parents: a block nested in another block is sharded first
        for block in reversed([m for m in net.modules() if isinstance(m, types)]):
            fully_shard(block, **options)
        fully_shard(module, **options)
