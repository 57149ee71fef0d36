"""Inference with the GAIA-2 latent world model: from scratch, autoregressive rollout, inpainting, scene editing,
with classifier-free guidance and spatially selective guidance (GAIA-2 report, inference).

Legend: b batch, v cameras, t latent steps, C h w latent channels and grid, k guided token positions.

Every mode integrates the flow ODE (gaia_app/diffusion/flow_matching.FlowSampler) with a velocity that keeps
known latents on their path: context steps stay clean (τ = 1), an inpainting mask's outside is replaced by
the known latents noised to the current τ. Outputs are latents; `VideoTokenizer.decode` makes frames.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import torch
from einops import rearrange

from gaia_app.diffusion.flow_matching import FlowSampler
from gaia_app.models.gaia2.conditioning import WorldConditions, project_boxes
from gaia_app.models.gaia2.latent_world_model import LatentWorldModel

SPATIAL_PASSES = ("agent_tokens", "full", "paired")


@dataclass
class Guidance:
    """Classifier-free guidance: v = v_u + scale·(v_c − v_u), v_u with `conditions` dropped.

    scale: 0 or 1 switches guidance off (one pass); the report uses 2–20 when it guides.
    spatial: guide only the token positions inside the projected agent boxes (spatially selective CFG); tokens
        elsewhere keep the conditional velocity.
    spatial_pass: how the second pass of spatial guidance runs: "agent_tokens" (the report's saving: the network
        sees only the agent tokens, so that pass loses the rest of the scene as context) or "full" (the
        straightforward variant: a full unconditional pass, whose velocity is used inside the agent regions only) or
        "paired" (the report's "dual pass only for the agent tokens": a conditional and an unconditional pass over the
        agent tokens alone give the guidance direction, so both sides of v_c − v_u lack the same scene; inside the
        boxes v = v_c + (scale − 1)·(v_c,agents − v_u,agents), v_c from the full conditional pass).
    interval: the flow times (lo, hi), τ = 0 noise … 1 data, at which a step is guided; elsewhere it takes the
        conditional velocity and skips the second pass. (0, 1), the default, guides every step. Guidance in a limited
        interval (Kynkäänniemi et al., NeurIPS 2024) keeps its pull on what forms at high noise (layout, motion)
        without pushing the fine detail of the last steps off the data.
    """

    scale: float = 0.0
    conditions: Sequence[str] = ("agents",)
    spatial: bool = False
    spatial_pass: str = "agent_tokens"
    interval: Sequence[float] = (0.0, 1.0)

    def __post_init__(self) -> None:
        if self.spatial_pass not in SPATIAL_PASSES:
            raise ValueError(f"guidance.spatial_pass={self.spatial_pass!r}: expected one of {SPATIAL_PASSES}")
        lo, hi = (float(x) for x in self.interval) if len(self.interval) == 2 else (None, None)
        if lo is None or not 0.0 <= lo < hi <= 1.0:
            raise ValueError(f"guidance.interval={list(self.interval)}: expected [lo, hi] with 0 ≤ lo < hi ≤ 1 "
                             "(flow time)")
        self.interval = (lo, hi)

    def applies(self, taus: torch.Tensor) -> torch.Tensor:
        """(b, t) True where flow time taus (b, t) lies in `interval`."""
        lo, hi = self.interval
        return (taus >= lo) & (taus <= hi)

    @property
    def active(self) -> bool:
        return self.scale not in (0.0, 1.0)


@dataclass
class TokenCounter:
    """Tokens the network evaluated (per step × positions), to compare guidance costs."""

    tokens: int = 0
    calls: list[int] = field(default_factory=list)

    def add(self, batch: int, steps: int, positions: int) -> None:
        self.calls.append(batch * steps * positions)
        self.tokens += self.calls[-1]


def agent_token_positions(cond: WorldConditions, grid: tuple[int, int], patch: int) -> torch.Tensor:
    """Indices (k,) into the v·(h/p)·(w/p) token positions covered by any visible agent box at any step
    (one set for every step, so temporal attention stays regular)."""
    if cond.agents is None:
        return torch.zeros(0, dtype=torch.long)
    boxes, _, visible = project_boxes(cond.agents, cond.intrinsics, cond.extrinsics, cond.image_size)  # (b, t, v, N, 4)
    gh, gw = grid[0] // patch, grid[1] // patch
    ys = (torch.arange(gh, device=boxes.device) + 0.5) / gh
    xs = (torch.arange(gw, device=boxes.device) + 0.5) / gw
    x0, y0, x1, y1 = (boxes[..., i, None, None] for i in range(4))
    # a token is inside when its cell overlaps the box (half a cell of slack on each side)
    cols = (xs + 0.5 / gw > x0) & (xs - 0.5 / gw < x1)  # (b, t, v, N, 1, gw)
    rows = (ys[:, None] + 0.5 / gh > y0) & (ys[:, None] - 0.5 / gh < y1)  # (b, t, v, N, gh, 1)
    inside = rows & cols & visible[..., None, None]  # (b, t, v, N, gh, gw)
    covered = inside.any(dim=3).any(dim=1).any(dim=0)  # (v, gh, gw)
    return torch.nonzero(rearrange(covered, "v h w -> (v h w)")).flatten()


class LatentWorldModelPipeline:
    """All inference modes of the latent world model.

    Args:
        model: the trained LatentWorldModel (eval mode).
        sampler: the ODE solver and τ grid (the report: Euler, 50 linear-quadratic steps).
        guidance: classifier-free guidance settings.
    """

    def __init__(self, model: LatentWorldModel, sampler: FlowSampler | None = None, guidance: Guidance | None = None):
        self.model = model.eval()
        self.sampler = sampler or FlowSampler()
        self.guidance = guidance or Guidance()
        self.counter = TokenCounter()

    # ---- velocity with guidance -------------------------------------------------------------

    def velocity(self, x: torch.Tensor, taus: torch.Tensor, cond: WorldConditions) -> torch.Tensor:
        """Guided velocity (b, v, t, C, h, w) at per-step flow times taus (b, t)."""
        b, v, t, _, h, w = x.shape
        conditional = self.model(x, taus, cond)
        self.counter.add(b, t, v * (h // self.model.patch) * (w // self.model.patch))
        g = self.guidance
        if not g.active:
            return conditional
        inside = g.applies(taus)
        if not inside.any():
            return conditional
        guided = self.guided(x, taus, cond, conditional)
        return torch.where(inside[:, None, :, None, None, None], guided, conditional)

    def guided(self, x: torch.Tensor, taus: torch.Tensor, cond: WorldConditions,
               conditional: torch.Tensor) -> torch.Tensor:
        """The guided velocity (b, v, t, C, h, w) from the conditional one: plain CFG, or spatially selective CFG."""
        b, v, t, _, h, w = x.shape
        p, g = self.model.patch, self.guidance
        positions = v * (h // p) * (w // p)
        unconditional_cond = cond.without(*g.conditions)
        if not g.spatial:
            unconditional = self.model(x, taus, unconditional_cond)
            self.counter.add(b, t, positions)
            return unconditional + g.scale * (conditional - unconditional)
        selected = agent_token_positions(cond, (h, w), p).to(x.device)
        if selected.numel() == 0:
            return conditional
        tokens = rearrange(conditional, "b v t c (h p) (w q) -> b t (v h w) (p q c)", p=p, q=p)
        picked = tokens[:, :, selected]
        if g.spatial_pass == "full":
            scene = self.model(x, taus, unconditional_cond)
            self.counter.add(b, t, positions)
            unconditional = rearrange(scene, "b v t c (h p) (w q) -> b t (v h w) (p q c)", p=p, q=p)[:, :, selected]
            direction = picked - unconditional
        else:
            unconditional = self.model(x, taus, unconditional_cond, positions=selected)  # (b, t, k, C·p²)
            self.counter.add(b, t, selected.numel())
            if g.spatial_pass == "paired":
                direction = self.model(x, taus, cond, positions=selected) - unconditional
                self.counter.add(b, t, selected.numel())
            else:
                direction = picked - unconditional
        tokens = tokens.clone()
        # v_u + s·(v_c − v_u) = v_c + (s − 1)·(v_c − v_u): the same formula for every pass, only the direction differs
        tokens[:, :, selected] = picked + (g.scale - 1.0) * direction
        return rearrange(tokens, "b t (v h w) (p q c) -> b v t c (h p) (w q)", v=v, h=h // p, p=p, q=p)

    def integrate(self, noise: torch.Tensor, cond: WorldConditions, clean: torch.Tensor | None = None,
                  clean_steps: int = 0, known: torch.Tensor | None = None, known_mask: torch.Tensor | None = None,
                  start: int = 0) -> torch.Tensor:
        """Integrate from `noise` (b, v, t, C, h, w). The first `clean_steps` steps are held at `clean` (τ = 1);
        where `known_mask` (b, v, t, 1, h, w) is True the sample is reset to `known` on its noise path."""
        def velocity(x: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
            taus = tau[:, None].expand(x.shape[0], x.shape[2]).clone()
            if clean_steps:
                x = torch.cat([clean[:, :, :clean_steps], x[:, :, clean_steps:]], dim=2)
                taus[:, :clean_steps] = 1.0
            if known_mask is not None:
                path = tau[:, None, None, None, None, None] * known + (1 - tau[:, None, None, None, None, None]) * noise
                x = torch.where(known_mask, path, x)
            out = self.velocity(x, taus, cond)
            if clean_steps:
                out = torch.cat([torch.zeros_like(out[:, :, :clean_steps]), out[:, :, clean_steps:]], dim=2)
            return out

        x = self.sampler(velocity, noise, start=start)
        if clean_steps:
            x = torch.cat([clean[:, :, :clean_steps], x[:, :, clean_steps:]], dim=2)
        if known_mask is not None:
            x = torch.where(known_mask, known, x)
        return x

    # ---- modes ----------------------------------------------------------------------------

    @torch.no_grad()
    def from_scratch(self, shape: tuple[int, ...], cond: WorldConditions, generator: torch.Generator | None = None
                     ) -> torch.Tensor:
        """Latents (b, v, t, C, h, w) generated from noise under `cond` alone."""
        return self.integrate(self.noise(shape, generator), cond)

    @torch.no_grad()
    def rollout(self, context: torch.Tensor, chunks: Sequence[WorldConditions], chunk_steps: int,
                generator: torch.Generator | None = None) -> torch.Tensor:
        """Autoregressive rollout: from clean `context` latents (b, v, c, C, h, w), generate `chunk_steps` steps
        per entry of `chunks` (each covering the c context steps + chunk_steps new ones, so new controls apply
        per chunk); every chunk becomes part of the next one's context (the last c steps). → (b, v, c + n·chunk, …)."""
        c = context.shape[2]
        video = context
        for cond in chunks:
            window = video[:, :, -c:]
            shape = (*window.shape[:2], c + chunk_steps, *window.shape[3:])
            x = self.integrate(self.noise(shape, generator, window.device), cond, clean=window, clean_steps=c)
            video = torch.cat([video, x[:, :, c:]], dim=2)
        return video

    @torch.no_grad()
    def inpaint(self, latents: torch.Tensor, mask: torch.Tensor, cond: WorldConditions,
                generator: torch.Generator | None = None) -> torch.Tensor:
        """Regenerate where `mask` (b, v, t, h, w) is True, keep `latents` elsewhere (e.g. insert an agent)."""
        known_mask = ~mask[:, :, :, None]
        return self.integrate(self.noise(latents.shape, generator, latents.device), cond, known=latents,
                              known_mask=known_mask.expand_as(latents))

    @torch.no_grad()
    def edit(self, latents: torch.Tensor, cond: WorldConditions, strength: float = 0.6,
             generator: torch.Generator | None = None) -> torch.Tensor:
        """Scene editing: noise a real clip's latents back to τ = 1 − strength and denoise under new conditions
        (strength 1: from scratch; 0: unchanged)."""
        taus = self.sampler.taus()
        start = int(torch.searchsorted(taus, torch.tensor(1.0 - strength)).clamp(0, self.sampler.steps))
        tau0 = float(taus[start])
        noise = self.noise(latents.shape, generator, latents.device)
        return self.integrate(tau0 * latents + (1 - tau0) * noise, cond, start=start)

    @staticmethod
    def noise(shape: Sequence[int], generator: torch.Generator | None,
              device: torch.device | str = "cpu") -> torch.Tensor:
        return torch.randn(*shape, generator=generator, device=device)


def with_window(cond: WorldConditions, steps: slice) -> WorldConditions:
    """The conditions of latent steps `steps` (per-step fields sliced, clip-level fields kept)."""
    agents = cond.agents
    if agents is not None:
        agents = replace(agents, centre=agents.centre[:, steps], size=agents.size[:, steps], yaw=agents.yaw[:, steps],
                         category=agents.category[:, steps], mask=agents.mask[:, steps])
    return replace(cond, timestamps=None if cond.timestamps is None else cond.timestamps[:, steps],
                   actions=None if cond.actions is None else cond.actions[:, steps], agents=agents)
