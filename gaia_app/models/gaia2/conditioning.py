"""Conditioning of the GAIA-2 latent world model: every signal the report lists, each optional and droppable.

Legend: b batch, v cameras, t latent steps, N agents per step, F metadata fields, e embedding widths,
d model width, m condition tokens per step.

Two routes (GAIA-2 report, world model):
- AdaLN, per latent step: flow time τ and ego action (speed, curvature) → c (b, t, d);
- cross-attention, per latent step: agent tokens (3-D boxes projected into each camera: 2-D box, depth,
  orientation, dimensions, category), one token per metadata field and a text/image (CLIP) vector → context
  (b, t, m, d) with a mask. The report's scenario embeddings come from a proprietary Wayve model; with no such
  model or labels to feed them, this implementation has no scenario input. A learned null token is always present, so
  attention never runs over nothing.
Optionally (`agent_raster`, off in the paper preset) the agent tokens are also painted onto the latent grid: each
token position receives the agent tokens of its camera weighted by how much of its cell their projected box covers.
Cross-attention must learn where a box lies from its coordinates; the raster says it at the right place, which a
small model trained briefly needs before agents show (docs/latent_world_model.md, "Agents painted on the grid").
Optionally (`action_raster`, off in the paper preset) the ego action is painted too, as the flow it causes in each
cell of each camera (gaia_app/models/gaia2/ego_flow.py).
Geometry is added to the tokens, not attended: each camera's intrinsics and extrinsics through an MLP
(one network serves any rig and any number of cameras), timestamps as sine-cosine features (variable
frame rates).

Dropping a condition (absent, or dropped for classifier-free guidance) masks its tokens out, or swaps
the action for a learned null action, so a dropped condition has exactly no effect.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import torch
from einops import rearrange
from torch import nn

from gaia_app.models.gaia2.ego_flow import ego_motion_flow, step_seconds
from gaia_app.nn.spacetime import sincos_1d, sincos_2d_at

CONDITIONS = ("action", "agents", "metadata", "text")
FLOW_UNIT = 2.0  # cells: ego-motion flows are divided by it before the action raster's MLP (most lie within ± 4)
# agent tokens (b, t, v, N, d), their 2-D boxes (b, t, v, N, 4) and visibility (b, t, v, N) in every camera
AgentFeatures = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


@dataclass
class AgentBoxes3d:
    """Agents per latent step in the ego frame: centre (b, t, N, 3) m, size (b, t, N, 3) length/width/height m,
    yaw (b, t, N) rad, category (b, t, N) int, mask (b, t, N) bool (False: padding)."""

    centre: torch.Tensor
    size: torch.Tensor
    yaw: torch.Tensor
    category: torch.Tensor
    mask: torch.Tensor


@dataclass
class WorldConditions:
    """Everything the latent world model can condition on; None = absent.

    intrinsics (b, v, 3, 3) and extrinsics (b, v, 4, 4, camera → ego) at `image_size` (H, W) are required:
    they say which camera each view is. timestamps (b, t) seconds; actions (b, t, 2) speed m/s and
    curvature 1/m per latent step; metadata {field: (b,) int64 index into that field's vocabulary};
    text (b, e_text) a CLIP text embedding (or a pooled token encoder's vector).
    `dropped` names conditions to ignore even when present (classifier-free guidance's second pass).
    """

    intrinsics: torch.Tensor
    extrinsics: torch.Tensor
    image_size: tuple[int, int]
    timestamps: torch.Tensor | None = None
    actions: torch.Tensor | None = None
    agents: AgentBoxes3d | None = None
    metadata: Mapping[str, torch.Tensor] | None = None
    text: torch.Tensor | None = None
    dropped: frozenset[str] = field(default_factory=frozenset)

    def without(self, *names: str) -> WorldConditions:
        """The same conditions with `names` dropped."""
        unknown = set(names) - set(CONDITIONS)
        if unknown:
            raise ValueError(f"unknown conditions {sorted(unknown)}; expected some of {CONDITIONS}")
        return replace(self, dropped=self.dropped | frozenset(names))

    def active(self, name: str) -> bool:
        """True when condition `name` is present and not dropped."""
        value = {"action": self.actions, "agents": self.agents, "metadata": self.metadata, "text": self.text}[name]
        return value is not None and name not in self.dropped


def box_corners(centre: torch.Tensor, size: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
    """(..., 3), (..., 3), (...) → the 8 corners (..., 8, 3) of yawed boxes in the ego frame (z up)."""
    signs = torch.tensor([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=centre.dtype,
                         device=centre.device) * 0.5
    local = signs * size[..., None, :]  # (..., 8, 3)
    cos, sin = yaw.cos()[..., None], yaw.sin()[..., None]
    x = cos * local[..., 0] - sin * local[..., 1]
    y = sin * local[..., 0] + cos * local[..., 1]
    return torch.stack([x, y, local[..., 2]], dim=-1) + centre[..., None, :]


def project_boxes(agents: AgentBoxes3d, intrinsics: torch.Tensor, extrinsics: torch.Tensor, image_size: tuple[int, int]
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Project every agent into every camera.

    Returns boxes (b, t, v, N, 4) as (x0, y0, x1, y1) / (W, H) clipped to [0, 1], depth (b, t, v, N) metres
    along the optical axis, and visible (b, t, v, N): a real agent with a corner in front of the camera
    and a box overlapping the image.
    """
    height, width = image_size
    corners = box_corners(agents.centre, agents.size, agents.yaw)  # (b, t, N, 8, 3)
    ego_to_cam = torch.linalg.inv(extrinsics)  # (b, v, 4, 4)
    rotation, translation = ego_to_cam[..., :3, :3], ego_to_cam[..., :3, 3]
    cam = torch.einsum("bvij,btnkj->btvnki", rotation, corners) + translation[:, None, :, None, None, :]
    z = cam[..., 2]
    in_front = z > 0.1
    pix = torch.einsum("bvij,btvnkj->btvnki", intrinsics, cam)
    uv = pix[..., :2] / z.clamp_min(0.1)[..., None]
    big = torch.finfo(uv.dtype).max
    lo = torch.where(in_front[..., None], uv, torch.full_like(uv, big)).amin(dim=-2)
    hi = torch.where(in_front[..., None], uv, torch.full_like(uv, -big)).amax(dim=-2)
    scale = uv.new_tensor([width, height])
    lo, hi = (lo / scale), (hi / scale)
    visible = in_front.any(-1) & (hi > 0).all(-1) & (lo < 1).all(-1) & agents.mask[:, :, None, :]
    boxes = torch.cat([lo.clamp(0, 1), hi.clamp(0, 1)], dim=-1)
    depth = torch.where(in_front, z, torch.zeros_like(z)).amax(dim=-1)
    return torch.where(visible[..., None], boxes, torch.zeros_like(boxes)), depth * visible, visible


def box_raster(boxes: torch.Tensor, visible: torch.Tensor, image_size: tuple[int, int]) -> torch.Tensor:
    """Pixel masks of boxes (..., N, 4) as (x0, y0, x1, y1) in [0, 1] (`project_boxes`) with visible (..., N):
    (..., H, W) bool, true at every pixel that overlaps a visible box (a box's edges round outwards)."""
    height, width = image_size
    ys = torch.arange(height, device=boxes.device, dtype=boxes.dtype) / height
    xs = torch.arange(width, device=boxes.device, dtype=boxes.dtype) / width
    x0, y0, x1, y1 = (boxes[..., i] for i in range(4))  # (..., N)
    across = (xs + 1 / width > x0[..., None]) & (xs < x1[..., None])  # (..., N, W)
    down = (ys + 1 / height > y0[..., None]) & (ys < y1[..., None]) & visible[..., None]  # (..., N, H)
    return (down[..., :, None] & across[..., None, :]).any(dim=-3)


def cell_coverage(boxes: torch.Tensor, grid: tuple[int, int]) -> torch.Tensor:
    """Share of each of the gh × gw cells of the unit image covered by each box: boxes (..., 4) as
    (x0, y0, x1, y1) in [0, 1] → (..., gh, gw) in [0, 1]."""
    gh, gw = grid
    edges_y = torch.linspace(0, 1, gh + 1, device=boxes.device, dtype=boxes.dtype)
    edges_x = torch.linspace(0, 1, gw + 1, device=boxes.device, dtype=boxes.dtype)
    x0, y0, x1, y1 = (boxes[..., i, None] for i in range(4))
    across = (torch.minimum(edges_x[1:], x1) - torch.maximum(edges_x[:-1], x0)).clamp_min(0) * gw  # (..., gw)
    down = (torch.minimum(edges_y[1:], y1) - torch.maximum(edges_y[:-1], y0)).clamp_min(0) * gh  # (..., gh)
    return down[..., :, None] * across[..., None, :]


def own_camera_coverage(boxes: torch.Tensor, visible: torch.Tensor, grid: tuple[int, int]) -> torch.Tensor:
    """(b, t, v·gh·gw, v·N) bool: agent j's projected box covers image token i's cell in i's own camera (the token
    and agent orders of the net's sequence and context). boxes (b, t, v, N, 4) in [0, 1], visible (b, t, v, N)."""
    cover = (cell_coverage(boxes, grid) > 0) & visible[..., None, None]  # (b, t, v, N, gh, gw)
    v = cover.shape[2]
    by_cell = rearrange(cover, "b t v n h w -> b t v (h w) 1 n")  # the query's camera v is the agent's
    same_camera = torch.eye(v, dtype=torch.bool, device=boxes.device)[:, None, :, None]  # (v, 1, u, 1)
    return rearrange(by_cell & same_camera, "b t v c u n -> b t (v c) (u n)")


def fourier(x: torch.Tensor, dim: int, scale: float) -> torch.Tensor:
    """Sine-cosine features (…, dim) of a scalar tensor (…) multiplied by `scale` (positions in that unit)."""
    return sincos_1d((x * scale).flatten(), dim).reshape(*x.shape, dim)


def mlp(inputs: int, dim: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(inputs, dim), nn.SiLU(), nn.Linear(dim, dim))


class WorldConditioner(nn.Module):
    """Turns WorldConditions into AdaLN vectors, a cross-attention context and geometry embeddings.

    Args:
        dim: d.
        metadata_fields: {field: vocabulary size} of categorical metadata (indices from
            gaia_app.data.metadata), one token per field.
        text_dim: width of the text/image vector (0: not used).
        agent_categories: number of agent categories.
        agent_raster: also paint the agent tokens onto the grid cells their boxes cover (`grid_agents`).
        action_raster: also paint each step's ego-motion flow onto every cell (`grid_actions`).
        agent_position_keys: add to each agent token the grid's own position code at its box centre and its
            camera's token embedding (`position_keys`), the codes its image tokens carry, so that cross-attention
            can match a token to the agents over it (DETR's shared positional codes); still cross-attention only.
        dropout: {condition: probability} of dropping it per sample while training (classifier-free
            guidance; the report: "aggressive" dropout).
    """

    def __init__(self, dim: int, metadata_fields: Mapping[str, int], text_dim: int = 0,
                 agent_categories: int = 8, dropout: Mapping[str, float] | None = None, agent_raster: bool = False,
                 action_raster: bool = False, agent_position_keys: bool = False):
        super().__init__()
        self.dim = dim
        self.agent_position_keys = agent_position_keys
        self.tau = mlp(dim, dim)
        self.action = mlp(2 * (dim // 2), dim)
        self.null_action = nn.Parameter(torch.zeros(dim))
        self.camera = mlp(4 + 12, dim)
        self.time = mlp(dim, dim)
        self.agent_geometry = mlp(4 + 1 + 2 + 3, dim)
        self.agent_category = nn.Embedding(agent_categories, dim)
        self.agent_camera = mlp(4 + 12, dim)
        self.agent_raster = nn.Linear(dim, dim) if agent_raster else None
        self.action_raster = mlp(2, dim) if action_raster else None
        self.metadata_fields = dict(metadata_fields)
        self.metadata = nn.ModuleDict({name: nn.Embedding(size, dim) for name, size in self.metadata_fields.items()})
        self.metadata_field = nn.Embedding(max(1, len(self.metadata_fields)), dim)
        self.text = nn.Linear(text_dim, dim) if text_dim else None
        self.null_token = nn.Parameter(torch.randn(dim) * 0.02)
        self.dropout = {name: float(p) for name, p in (dropout or {}).items()}
        unknown = set(self.dropout) - set(CONDITIONS)
        if unknown:
            raise ValueError(f"conditioning dropout for unknown conditions {sorted(unknown)}; expected {CONDITIONS}")

    # ---- per-step vectors and geometry -------------------------------------------------------

    def adaln(self, tau: torch.Tensor, cond: WorldConditions, keep: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """c (b, t, d) = MLP(τ) + MLP(action) (or the null action when absent/dropped). tau (b, t)."""
        c = self.tau_embedding(tau)
        if cond.active("action"):
            action = torch.where(keep["action"][:, None, None], self.action_embedding(cond.actions), self.null_action)
            return c + action
        return c + self.null_action

    def tau_embedding(self, tau: torch.Tensor) -> torch.Tensor:
        """(…, d) the flow time's part of the AdaLN vector; tau (…)."""
        return self.tau(fourier(tau, self.dim, 1000.0))

    def action_embedding(self, actions: torch.Tensor) -> torch.Tensor:
        """(…, d) the ego action's part of the AdaLN vector; actions (…, 2) speed m/s and curvature 1/m."""
        return self.action(self.action_features(actions))

    def action_features(self, actions: torch.Tensor) -> torch.Tensor:
        """(…, d) the Fourier features the action MLP reads: speed in m/s, curvature in 1/(100 m), d/2 each."""
        speed, curvature = actions[..., 0], actions[..., 1]
        return torch.cat([fourier(speed, self.dim // 2, 1.0), fourier(curvature, self.dim // 2, 100.0)], dim=-1)

    def camera_features(self, cond: WorldConditions) -> torch.Tensor:
        """(b, v, 16): focal lengths and principal point over the image size, rotation and translation (m)."""
        height, width = cond.image_size
        k = cond.intrinsics
        intr = torch.stack([k[..., 0, 0] / width, k[..., 1, 1] / height, k[..., 0, 2] / width,
                            k[..., 1, 2] / height], -1)
        extr = torch.cat([cond.extrinsics[..., :3, :3].flatten(-2), cond.extrinsics[..., :3, 3]], dim=-1)
        return torch.cat([intr, extr], dim=-1)

    def camera_embedding(self, cond: WorldConditions) -> torch.Tensor:
        """(b, v, d) added to every token of each camera."""
        return self.camera(self.camera_features(cond))

    def time_embedding(self, cond: WorldConditions, steps: int, device: torch.device) -> torch.Tensor:
        """(b or 1, t, d) from timestamps in seconds (absent: zeros, the model then relies on step order)."""
        if cond.timestamps is None:
            return torch.zeros(1, steps, self.dim, device=device)
        return self.time(fourier(cond.timestamps - cond.timestamps[:, :1], self.dim, 10.0))

    # ---- cross-attention context ----------------------------------------------------------

    def keep_masks(self, b: int, device: torch.device) -> dict[str, torch.Tensor]:
        """(b,) bool per condition: False where this sample's condition is dropped (training dropout)."""
        keep = {}
        for name in CONDITIONS:
            p = self.dropout.get(name, 0.0) if self.training else 0.0
            keep[name] = torch.rand(b, device=device) >= p if p > 0 else torch.ones(b, dtype=torch.bool, device=device)
        return keep

    def context(self, cond: WorldConditions, b: int, t: int, keep: Mapping[str, torch.Tensor], device: torch.device,
                agents: AgentFeatures | None = None, box_grid: tuple[int, int] | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """(b, t, m, d) tokens and (b, t, m) mask: null, agents (v·N), metadata (F), text. agents: the
        `agent_features` of cond when the caller has them already. box_grid (gh, gw): the mask per image token
        instead, (b, t, v·gh·gw, m), each token's agent keys kept only for the agents whose boxes cover its cell in
        its own camera (agent_box_attention; the other keys as for every token)."""
        tokens = [self.null_token.expand(b, t, 1, self.dim)]
        masks = [torch.ones(b, t, 1, dtype=torch.bool, device=device)]
        own = None  # with box_grid: (b, t, v·cells, v·N), which agents each image token may read
        if cond.active("agents"):
            agents = agents if agents is not None else self.agent_features(cond, box_grid)
            agent_tokens, visible = self.agent_tokens(cond, agents)
            tokens.append(agent_tokens)
            masks.append(visible & keep["agents"][:, None, None])
            if box_grid is not None:
                own = own_camera_coverage(agents[1], agents[2], box_grid)
        if cond.active("metadata"):
            meta = self.metadata_tokens(cond.metadata, b)
            tokens.append(meta[:, None].expand(b, t, -1, -1))
            masks.append((keep["metadata"][:, None, None]).expand(b, t, meta.shape[1]))
        if cond.active("text"):
            if self.text is None:
                raise ValueError("WorldConditions.text given, but the model was built with text_dim=0")
            tokens.append(self.text(cond.text)[:, None, None].expand(b, t, 1, self.dim))
            masks.append(keep["text"][:, None, None].expand(b, t, 1))
        mask = torch.cat(masks, dim=2)
        if own is not None:
            mask = mask[:, :, None].expand(-1, -1, own.shape[2], -1).clone()
            mask[..., 1 : 1 + own.shape[-1]] &= own  # the agent keys, right after the null token
        return torch.cat(tokens, dim=2), mask

    def agent_tokens(self, cond: WorldConditions, agents: AgentFeatures | None = None
                     ) -> tuple[torch.Tensor, torch.Tensor]:
        """Agents projected into each camera → tokens (b, t, v·N, d) and visibility (b, t, v·N)."""
        tokens, _, visible = agents if agents is not None else self.agent_features(cond)
        return rearrange(tokens, "b t v n d -> b t (v n) d"), rearrange(visible, "b t v n -> b t (v n)")

    def grid_agents(self, agents: AgentFeatures, grid: tuple[int, int], keep: Mapping[str, torch.Tensor]
                    ) -> torch.Tensor:
        """(b, t, v, gh, gw, d): per grid cell, Σ over agents of (share of the cell their box covers) · agent token,
        projected (agent_raster). agents: `agent_features`; grid (gh, gw) token cells per camera."""
        tokens, boxes, visible = agents
        cover = cell_coverage(boxes, grid) * (visible & keep["agents"][:, None, None, None])[..., None, None]
        painted = torch.einsum("btvnhw,btvnd->btvhwd", cover.to(tokens.dtype), tokens)
        return self.agent_raster(painted)

    def grid_actions(self, cond: WorldConditions, grid: tuple[int, int], keep: Mapping[str, torch.Tensor]
                     ) -> torch.Tensor:
        """(b, t, v, gh, gw, d): each cell's ego-motion flow under its step's action (ego_flow.ego_motion_flow),
        embedded (action_raster); zero where the action is dropped. grid (gh, gw) token cells per camera."""
        steps = cond.actions.shape[1]
        flow = ego_motion_flow(cond.actions, step_seconds(cond.timestamps, steps), cond.intrinsics, cond.extrinsics,
                               cond.image_size, grid)
        painted = self.action_raster(flow / FLOW_UNIT)
        return painted * keep["action"][:, None, None, None, None, None].to(painted.dtype)

    def agent_features(self, cond: WorldConditions, grid: tuple[int, int] | None = None) -> AgentFeatures:
        """Agent tokens (b, t, v, N, d), their boxes (b, t, v, N, 4) and visibility (b, t, v, N) in every camera.
        grid (gh, gw): the token cells per camera, needed with agent_position_keys."""
        agents = cond.agents
        boxes, depth, visible = project_boxes(agents, cond.intrinsics, cond.extrinsics, cond.image_size)
        v = boxes.shape[2]
        yaw = agents.yaw[:, :, None].expand(-1, -1, v, -1)
        size = agents.size[:, :, None].expand(-1, -1, v, -1, -1)
        geometry = torch.cat([boxes, torch.log1p(depth)[..., None], yaw.sin()[..., None], yaw.cos()[..., None],
                              torch.log1p(size)], dim=-1)
        tokens = self.agent_geometry(geometry) + self.agent_category(agents.category)[:, :, None]
        tokens = tokens + self.agent_camera(self.camera_features(cond))[:, None, :, None]
        if self.agent_position_keys:
            tokens = tokens + self.position_keys(cond, boxes, grid)
        return tokens, boxes, visible

    def position_keys(self, cond: WorldConditions, boxes: torch.Tensor, grid: tuple[int, int] | None
                      ) -> torch.Tensor:
        """(b, t, v, N, d): `sincos_2d_at` of each box centre in token cells (cell i's centre at i, as the grid's
        table) plus the camera embedding its camera's image tokens get. boxes (b, t, v, N, 4) in [0, 1]."""
        if grid is None:
            raise ValueError("agent_position_keys: agent_features needs the token grid (gh, gw)")
        rows = (boxes[..., 1] + boxes[..., 3]) / 2 * grid[0] - 0.5
        cols = (boxes[..., 0] + boxes[..., 2]) / 2 * grid[1] - 0.5
        return sincos_2d_at(rows, cols, self.dim).to(boxes.dtype) + self.camera_embedding(cond)[:, None, :, None]

    def metadata_tokens(self, metadata: Mapping[str, torch.Tensor], b: int) -> torch.Tensor:
        """(b, F, d): one token per known field present, its value embedding plus a field embedding."""
        unknown = set(metadata) - set(self.metadata_fields)
        if unknown:
            raise ValueError(f"metadata fields {sorted(unknown)} are not in the model's metadata_fields "
                             f"{sorted(self.metadata_fields)}")
        tokens = []
        for i, name in enumerate(sorted(metadata)):
            index = metadata[name]
            size = self.metadata_fields[name]
            if index.shape != (b,) or index.min() < 0 or index.max() >= size:
                raise ValueError(f"metadata['{name}']: expected (b={b},) indices in [0, {size}), got "
                                 f"{tuple(index.shape)} in [{int(index.min())}, {int(index.max())}]")
            field_id = self.metadata_field.weight[list(self.metadata_fields).index(name)]
            tokens.append(self.metadata[name](index) + field_id)
        return torch.stack(tokens, dim=1)


def batch_conditions(batch: dict[str, Any], text: torch.Tensor | None = None) -> WorldConditions:
    """WorldConditions of a latent-window batch (absent labels stay None)."""
    if "intrinsics" not in batch:
        raise ValueError("latent batch has no camera intrinsics/extrinsics: the GAIA-2 world model needs the rig "
                         "(conditions.json 'cameras' of the latent cache)")
    agents = None
    if "agents_centre" in batch:
        agents = AgentBoxes3d(batch["agents_centre"], batch["agents_size"], batch["agents_yaw"],
                              batch["agents_category"], batch["agents_mask"])
    return WorldConditions(batch["intrinsics"], batch["extrinsics"], tuple(batch["image_size"]),
                           timestamps=batch.get("timestamps"), actions=batch.get("actions"), agents=agents,
                           metadata=batch.get("metadata") or None, text=text)


def caption_vector(text_encoder: Callable[[list[list[str]]], torch.Tensor], captions: Sequence[str]) -> torch.Tensor:
    """(b, e) text vector of one caption per sample (the report conditions on CLIP embeddings): the encoder's own
    `pooled` embedding where it has one (CLIPTextEncoder), else the mean of its token features (a token encoder
    such as MiniLM, [[caption]] per sample → (b, 1, m, e))."""
    pooled = getattr(text_encoder, "pooled", None)
    if pooled is not None:
        return pooled(list(captions))
    return text_encoder([[caption] for caption in captions])[:, 0].mean(dim=1)


def batch_text_vector(text_encoder: Callable[[list[list[str]]], torch.Tensor] | None,
                      batch: dict[str, Any]) -> torch.Tensor | None:
    """(b, e) `caption_vector` of a latent-window batch's captions in the dtype of its latents, or None without
    captions or without a text encoder (training and inference share it, so both read captions the same way)."""
    if text_encoder is None or "text" not in batch:
        return None
    return caption_vector(text_encoder, batch["text"]).to(batch["mean"].dtype)
