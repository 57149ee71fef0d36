"""GAIA-2 latent world model: a space-time factorised transformer over multi-camera latents that predicts the
flow-matching velocity (GAIA-2 report, world model).

Legend:
    b batch, v cameras, t latent steps, C latent channels, h w latent grid, p patch side,
    n = v·(h/p)·(w/p) tokens per step (every camera's), d width, m condition tokens per step.

Input latents `b v t C h w` at flow time τ (b, t) — context steps are clean (τ = 1), generated steps
noisy — and WorldConditions; output the velocity `b v t C h w` (x − ε, gaia_app/diffusion/flow_matching.py).

Spatial attention runs over the tokens of all cameras at one step (so views agree), temporal attention
over the steps of each token position. Tokens carry a 2-D sine-cosine position within their camera's
grid, their camera's geometry embedding and their step's timestamp embedding; nothing depends on the
number of cameras, so a model trained on one rig samples another.

`positions` (optional) selects a subset of the v·(h/p)·(w/p) token positions, identical at every step:
the network then runs on those tokens only (their embeddings are those of the full grid). Spatially
selective classifier-free guidance evaluates its second pass this way, on the tokens inside agent boxes.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from einops import rearrange
from torch import nn
from torch.utils.checkpoint import checkpoint

from gaia_app.models.gaia2.conditioning import AgentFeatures, WorldConditioner, WorldConditions
from gaia_app.nn.spacetime import AdaLNSpaceTimeBlock, sincos_2d


class LatentWorldModel(nn.Module):
    """Velocity network v(x_τ, τ, conditions) over multi-camera latents.

    Args:
        latent_channels: C of the video tokenizer (paper 64).
        patch_size: p, latent positions per token side (1: one token per latent position).
        dim, depth, heads, mlp_ratio: transformer (paper 22 layers, ≈ 8.4B parameters).
        metadata_fields, text_dim, agent_categories, condition_dropout, agent_raster, action_raster,
            agent_position_keys: see WorldConditioner.
        agent_position_queries: with agent_position_keys, also add each image token's own position code (the
            grid's sin-cos code and its camera's embedding, the codes the keys get at the box centre) to the
            cross-attention's queries in every block, as DETR does; the residual stream itself is unchanged.
        agent_box_attention: each image token's cross-attention reads only the agents whose projected boxes cover
            its cell in its own camera (and every null, metadata and text token; `WorldConditioner.context` with
            box_grid), a masked cross-attention in the manner of Mask2Former; nothing is painted on the grid.
        checkpointing: activation checkpointing of the blocks.
    """

    block_types: tuple[type[nn.Module], ...] = (AdaLNSpaceTimeBlock,)

    def __init__(self, latent_channels: int = 64, patch_size: int = 1, dim: int = 512, depth: int = 8, heads: int = 8,
                 mlp_ratio: float = 4.0, metadata_fields: Mapping[str, int] | None = None, text_dim: int = 0,
                 agent_categories: int = 8, condition_dropout: Mapping[str, float] | None = None,
                 checkpointing: bool = False, agent_raster: bool = False, action_raster: bool = False,
                 agent_position_keys: bool = False, agent_position_queries: bool = False,
                 agent_box_attention: bool = False):
        super().__init__()
        if agent_position_queries and not agent_position_keys:
            raise ValueError("agent_position_queries=True needs agent_position_keys=True: the queries' position codes "
                             "match nothing in agent tokens without keys")
        self.agent_position_queries = agent_position_queries
        self.agent_box_attention = agent_box_attention
        self.latent_channels, self.patch, self.dim = latent_channels, patch_size, dim
        self.patch_in = nn.Linear(latent_channels * patch_size**2, dim)
        self.conditioner = WorldConditioner(dim, metadata_fields or {}, text_dim, agent_categories,
                                            condition_dropout, agent_raster, action_raster, agent_position_keys)
        self.blocks = nn.ModuleList(AdaLNSpaceTimeBlock(dim, heads, dim, mlp_ratio) for _ in range(depth))
        self.norm_out = nn.LayerNorm(dim, elementwise_affine=False)
        self.modulation_out = nn.Sequential(nn.SiLU(), nn.Linear(dim, 2 * dim))
        self.patch_out = nn.Linear(dim, latent_channels * patch_size**2)
        self.checkpointing = checkpointing
        self.initialize_weights()

    def initialize_weights(self) -> None:
        """Xavier linears; zero output projection and output modulation, so the untrained model predicts v = 0
        (DiT's adaLN-Zero). The blocks zero their own modulations."""
        for module in self.modules():
            if isinstance(module, nn.Linear):
                nn.init.xavier_uniform_(module.weight)
                if module.bias is not None:
                    nn.init.zeros_(module.bias)
        for block in self.blocks:
            nn.init.zeros_(block.modulation[-1].weight)
            nn.init.zeros_(block.modulation[-1].bias)
        zeroed = [self.modulation_out[-1], self.patch_out]
        if self.conditioner.agent_raster is not None:  # agents start with no effect, as through the cross-attention
            zeroed.append(self.conditioner.agent_raster)
        if self.conditioner.action_raster is not None:  # likewise the action's flow
            zeroed.append(self.conditioner.action_raster[-1])
        for layer in zeroed:
            nn.init.zeros_(layer.weight)
            nn.init.zeros_(layer.bias)

    def check(self, x: torch.Tensor, tau: torch.Tensor, cond: WorldConditions) -> None:
        """Raise ValueError naming the tensor whose shape breaks the contract."""
        if x.ndim != 6 or x.shape[3] != self.latent_channels:
            raise ValueError(f"LatentWorldModel expects latents (b, v, t, C={self.latent_channels}, h, w); "
                             f"got {tuple(x.shape)}")
        b, v, t, _, h, w = x.shape
        if h % self.patch or w % self.patch:
            raise ValueError(f"latent grid {h}×{w} is not divisible by patch_size={self.patch}")
        if tau.shape != (b, t):
            raise ValueError(f"tau: expected (b, t) = ({b}, {t}), got {tuple(tau.shape)}")
        if cond.intrinsics.shape != (b, v, 3, 3) or cond.extrinsics.shape != (b, v, 4, 4):
            raise ValueError(f"conditions: intrinsics {tuple(cond.intrinsics.shape)} / extrinsics "
                             f"{tuple(cond.extrinsics.shape)}, expected ({b}, {v}, 3, 3) / ({b}, {v}, 4, 4)")
        if cond.actions is not None and cond.actions.shape != (b, t, 2):
            raise ValueError(f"conditions.actions: expected (b, t, 2) = ({b}, {t}, 2), got {tuple(cond.actions.shape)}")

    def embed(self, x: torch.Tensor, cond: WorldConditions, keep: Mapping[str, torch.Tensor],
              agents: AgentFeatures | None = None, codes: torch.Tensor | None = None) -> torch.Tensor:
        """Latents (b, v, t, C, h, w) → tokens (b, t, n, d) with position and camera codes (`position_codes`, computed
        here unless the caller has them) and time embeddings, and the
        agents (the conditioner's `agent_features`) painted on the grid when it has agent_raster and `keep` keeps them,
        and each step's ego-motion flow when it has action_raster and the action is active."""
        b, v, t, _, h, w = x.shape
        p = self.patch
        tokens = self.patch_in(rearrange(x, "b v t c (h p) (w q) -> b t v (h w) (p q c)", p=p, q=p))
        if codes is None:
            codes = self.position_codes(cond, (h // p, w // p))
        time = self.conditioner.time_embedding(cond, t, x.device)[:, :, None, None]  # (b, t, 1, 1, d)
        tokens = tokens + codes + time
        if agents is not None and self.conditioner.agent_raster is not None:
            painted = self.conditioner.grid_agents(agents, (h // p, w // p), keep)
            tokens = tokens + rearrange(painted, "b t v h w d -> b t v (h w) d")
        if self.conditioner.action_raster is not None and cond.active("action"):
            flow = self.conditioner.grid_actions(cond, (h // p, w // p), keep)
            tokens = tokens + rearrange(flow, "b t v h w d -> b t v (h w) d")
        return rearrange(tokens, "b t v n d -> b t (v n) d")

    def position_codes(self, cond: WorldConditions, grid: tuple[int, int]) -> torch.Tensor:
        """(b, 1, v, gh·gw, d): each image token's grid sin-cos code plus its camera's embedding, what `embed` adds
        to it, the cross-attention queries get with agent_position_queries, and `WorldConditioner.position_keys`
        gives an agent at its box centre."""
        camera = self.conditioner.camera_embedding(cond)  # (b, v, d)
        space = sincos_2d(*grid, self.dim, cond.intrinsics.device).to(camera.dtype)  # (gh·gw, d)
        return (space[None, None] + camera[:, :, None])[:, None]

    def forward(self, x: torch.Tensor, tau: torch.Tensor, cond: WorldConditions,
                positions: torch.Tensor | None = None) -> torch.Tensor:
        """x (b, v, t, C, h, w), τ (b, t) → velocity (b, v, t, C, h, w); with `positions` (k,) indices into
        the n = v·(h/p)·(w/p) token positions, only those tokens are computed: → (b, t, k, C·p²)."""
        self.check(x, tau, cond)
        b, v, t, _, h, w = x.shape
        keep = self.conditioner.keep_masks(b, x.device)
        # agent tokens once per forward: both the grid painting and the cross-attention use them
        grid = (h // self.patch, w // self.patch)
        agents = self.conditioner.agent_features(cond, grid) if cond.active("agents") else None
        codes = self.position_codes(cond, grid)
        tokens = self.embed(x, cond, keep, agents, codes)
        queries = rearrange(codes, "b 1 v n d -> b 1 (v n) d") if self.agent_position_queries else None
        if positions is not None:
            tokens = tokens[:, :, positions]
            queries = None if queries is None else queries[:, :, positions]
        c = self.conditioner.adaln(tau, cond, keep)
        context, mask = self.conditioner.context(cond, b, t, keep, x.device, agents,
                                                 grid if self.agent_box_attention else None)
        if mask.ndim == 4 and positions is not None:  # one mask row per image token (agent_box_attention)
            mask = mask[:, :, positions]
        for block in self.blocks:
            if self.checkpointing and self.training:
                tokens = checkpoint(block, tokens, c, context, mask, queries, use_reentrant=False)
            else:
                tokens = block(tokens, c, context, mask, queries)
        shift, scale = self.modulation_out(c).chunk(2, dim=-1)
        out = self.patch_out(self.norm_out(tokens) * (1 + scale[:, :, None]) + shift[:, :, None])
        if positions is not None:
            return out
        p = self.patch
        return rearrange(out, "b t (v h w) (p q c) -> b v t c (h p) (w q)", v=v, h=h // p, p=p, q=p)
