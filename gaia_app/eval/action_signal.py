"""Where a GAIA-1 world model's action (or text) signal goes: attention, gradients and the residual stream (issue 50,
item 2).

GAIA-1 §2.1/§2.3 give each step's action as l = 2 tokens (speed, curvature) after the step's image tokens, and its
caption as m text tokens before them; every image token has to find either by attention. Before scaling a model
whose futures ignore their commands or prompts, these numbers say at which point the signal is lost
(docs/paper_faithful.md reads them). The stream is the actions unless `stream="text"` is asked; below, "the stream's
tokens" are the action tokens or the text tokens, and "null" drops that stream to its learned null embedding:

- attention mass on the stream's tokens, per layer and head, at the positions that predict image tokens of steps
  1..T−1, over all its visible tokens and over the nearest ones (actions: those of the previous step, the command
  that moved the ego to this frame; text: this step's own caption), beside the uniform share (visible stream
  tokens ÷ visible positions) a head with no preference would give;
- the stream's direct write: the norm of what attention copies from its positions into the residual stream
  (Σ_heads Σ_{j ∈ stream} p_ij · W_o v_j), divided by the norm of the residual stream it is added to;
- the counterfactual share: ‖h_l(stream) − h_l(null)‖ ÷ ‖h_l(stream)‖ at those positions after the embedding
  (l = 0) and after every block, which also counts paths that bypass attention (the action shortcut);
- gradients of the next-token loss: the mean norm of ∂L/∂x per input position of each kind (action, image, text),
  and the gradient norms of the stream's projection (action embedding or text projection) beside the image-token
  embedding's;
- the effect on the prediction: KL(p(·| stream) ‖ p(·| null)) per image token, in nats.

The other stream is held at its null embedding throughout: the actions-only and text-only modes of GAIA-1 §4.2.

Legend: b windows, T steps per window, n image tokens per step, l action tokens per step, s = m + n + l positions per
step, L = T·s positions, d width, h query heads.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import torch

from gaia_app.models.gaia1.world_model import Conditions, WorldModel, next_token_loss


@dataclass
class Layout:
    """Where each kind of position sits in a window of `steps` steps of a WorldModel (GAIA-1 §2.1: c_t, z_t, a_t)."""

    m: int
    n: int
    l: int  # noqa: E741 (the paper's and world_model.py's name for the action tokens per step)
    steps: int

    @property
    def step_len(self) -> int:
        return self.m + self.n + self.l

    def predicting(self, step: int) -> torch.Tensor:
        """(n,) positions whose hidden state predicts z_{step, 0..n−1} (the last text token, then image tokens)."""
        return torch.arange(self.n) + step * self.step_len + self.m - 1

    def kinds(self) -> dict[str, torch.Tensor]:
        """(L,) bool masks of the text, image and action positions of the window."""
        slot = torch.arange(self.steps * self.step_len) % self.step_len
        return {"text": slot < self.m, "image": (slot >= self.m) & (slot < self.m + self.n),
                "actions": slot >= self.m + self.n}

    def previous_actions(self, step: int) -> torch.Tensor:
        """(l,) positions of the action tokens of step − 1."""
        return torch.arange(self.l) + (step - 1) * self.step_len + self.m + self.n

    def own_text(self, step: int) -> torch.Tensor:
        """(m,) positions of the text tokens of `step` (its caption, read before its image tokens)."""
        return torch.arange(self.m) + step * self.step_len

    def nearest(self, stream: str, step: int) -> torch.Tensor:
        """The stream's tokens closest in meaning to z_step: the previous step's actions, or this step's caption."""
        return self.previous_actions(step) if stream == "actions" else self.own_text(step)


@dataclass
class Accumulator:
    """Running sums of per-query statistics, averaged at the end."""

    sums: dict[str, torch.Tensor] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)

    def add(self, name: str, values: torch.Tensor, count: int) -> None:
        """values: the sum over `count` samples (any shape, the same every time)."""
        self.sums[name] = self.sums.get(name, 0) + values.detach().double()
        self.counts[name] = self.counts.get(name, 0) + count

    def mean(self, name: str) -> torch.Tensor:
        return self.sums[name] / max(self.counts[name], 1)


def block_inputs(net: WorldModel, tokens: torch.Tensor, cond: Conditions) -> list[torch.Tensor]:
    """The residual stream (b, L, d) entering every block, then the last block's output (before the final norm)."""
    streams: list[torch.Tensor] = []
    hooks = [block.register_forward_pre_hook(lambda _m, args: streams.append(args[0]))
             for block in net.transformer.blocks]
    hooks.append(net.transformer.blocks[-1].register_forward_hook(lambda _m, _a, out: streams.append(out)))
    try:
        net.decode(net.embed(tokens, cond))
    finally:
        for hook in hooks:
            hook.remove()
    return streams


def attention_statistics(net: WorldModel, streams: list[torch.Tensor], layout: Layout, acc: Accumulator,
                         stream: str = "actions") -> None:
    """Adds, per layer and head, the attention mass on the stream's tokens and their direct write share (module
    doc)."""
    kinds = layout.kinds()
    of_stream = kinds[stream].to(streams[0].device)
    rotary_net = net.transformer.rotary
    for layer, block in enumerate(net.transformer.blocks):
        x = streams[layer]
        normed = block.norm1(x)
        rotary = rotary_net(0, x.shape[1], x.device) if rotary_net is not None else None
        writes = block.attn.value_writes(normed)  # (b, h, L, d)
        for step in range(1, layout.steps):
            queries = layout.predicting(step).to(x.device)
            probs = block.attn.attention_probs(normed, queries, rotary)  # (b, h, k, L)
            on_stream = probs * of_stream  # (b, h, k, L)
            nearest = torch.zeros_like(of_stream)
            nearest[layout.nearest(stream, step).to(x.device)] = True
            visible = (torch.arange(x.shape[1], device=x.device)[None] <= queries[:, None])  # (k, L)
            uniform = (visible & of_stream).sum(-1) / visible.sum(-1)  # (k,)
            write = torch.einsum("bhkj,bhjd->bhkd", on_stream, writes)  # per head: (b, h, k, d)
            residual = x[:, queries].norm(dim=-1)[:, None]  # (b, 1, k)
            count = probs.shape[0] * probs.shape[2]
            acc.add(f"mass_all/{layer}", on_stream.sum(-1).sum((0, 2)), count)  # (h,)
            acc.add(f"mass_nearest/{layer}", (probs * nearest).sum(-1).sum((0, 2)), count)
            acc.add(f"uniform_all/{layer}", uniform.sum() * probs.shape[0], count)
            acc.add(f"write_head/{layer}", (write.norm(dim=-1) / residual).sum((0, 2)), count)
            acc.add(f"write/{layer}", (write.sum(1).norm(dim=-1) / residual[:, 0]).sum(), count)


def counterfactual_statistics(net: WorldModel, kept: list[torch.Tensor], dropped: list[torch.Tensor],
                              layout: Layout, acc: Accumulator) -> None:
    """Adds ‖h(stream) − h(null)‖ ÷ ‖h(stream)‖ at the predicting positions of steps 1..T−1, per layer."""
    queries = torch.cat([layout.predicting(step) for step in range(1, layout.steps)]).to(kept[0].device)
    for layer, (a, b) in enumerate(zip(kept, dropped, strict=True)):
        a, b = a[:, queries], b[:, queries]
        acc.add(f"counterfactual/{layer}", ((a - b).norm(dim=-1) / a.norm(dim=-1)).sum(), a.shape[0] * a.shape[1])


def prediction_kl(net: WorldModel, tokens: torch.Tensor, kept: Conditions, dropped: Conditions,
                  acc: Accumulator) -> None:
    """Adds KL(p(·| stream) ‖ p(·| null)) per image token of steps 1..T−1, nats."""
    log_kept = net(tokens, kept)[:, 1:].log_softmax(-1)
    log_null = net(tokens, dropped)[:, 1:].log_softmax(-1)
    kl = (log_kept.exp() * (log_kept - log_null)).sum(-1)
    acc.add("kl", kl.sum(), kl.numel())


def gradient_statistics(net: WorldModel, tokens: torch.Tensor, actions: torch.Tensor, layout: Layout,
                        acc: Accumulator, stream: str = "actions", text: torch.Tensor | None = None) -> None:
    """Adds the mean ‖∂L/∂x‖ per input position of each kind and the embedding parameters' gradient norms."""
    inputs: list[torch.Tensor] = []

    def keep_grad(_module: Any, args: tuple[torch.Tensor, ...]) -> None:
        args[0].retain_grad()
        inputs.append(args[0])

    hook = net.transformer.register_forward_pre_hook(keep_grad)
    net.zero_grad(set_to_none=True)
    try:
        with torch.enable_grad():
            next_token_loss(net, tokens, conditions(net, actions, False, text, stream)).backward()
    finally:
        hook.remove()
    per_position = inputs[0].grad.norm(dim=-1)  # (b, L)
    kinds = layout.kinds()
    # the last step's actions come after every image token of the window: nothing reads them
    kinds["actions"] &= torch.arange(len(kinds["actions"])) < (layout.steps - 1) * layout.step_len
    for kind, mask in kinds.items():
        values = per_position[:, mask.to(per_position.device)]
        acc.add(f"grad_input/{kind}", values.sum(), values.numel())
    conditioner = net.conditioner
    if stream == "actions":
        params = {"action_weight": conditioner.action_weight, "action_bias": conditioner.action_bias}
        if conditioner.action_deltas:
            params["delta_weight"] = conditioner.delta_weight
    else:
        params = {"text_weight": conditioner.text_proj.weight, "text_bias": conditioner.text_proj.bias}
    params["token_embedding"] = net.token_embedding.weight
    for name, param in params.items():
        acc.add(f"grad_param/{name}", param.grad.norm(), 1)
        acc.add(f"grad_relative/{name}", param.grad.norm() / param.detach().norm().clamp_min(1e-12), 1)
    net.zero_grad(set_to_none=True)


STREAMS = ("actions", "text")


def conditions(net: WorldModel, actions: torch.Tensor, drop: bool, text: torch.Tensor | None = None,
               stream: str = "actions") -> Conditions:
    """The stream kept (or replaced by its null embedding), the other one always null: the actions-only or text-only
    mode of GAIA-1 §4.2. actions: (b, T, l); text: (b, T, m, e) encoded captions, needed for stream "text"."""
    return net.conditioner(actions.shape[0], actions.shape[1], text if stream == "text" else None,
                           actions if stream == "actions" else None,
                           {"text": stream != "text" or drop, "actions": stream != "actions" or drop})


def check_window(net: WorldModel, tokens: torch.Tensor, actions: torch.Tensor, text: torch.Tensor | None,
                 stream: str) -> None:
    if tokens.shape[:2] != actions.shape[:2] or tokens.shape[2] != net.n or actions.shape[2] != net.l:
        raise ValueError(f"windows: tokens {tuple(tokens.shape)} and actions {tuple(actions.shape)} do not fit a "
                         f"model of n={net.n} image and l={net.l} action tokens per step")
    if stream == "text" and (text is None or text.shape[:3] != (*tokens.shape[:2], net.m)):
        got = "none" if text is None else tuple(text.shape)
        raise ValueError(f"windows: stream 'text' needs encoded captions (b, T, m={net.m}, e) beside tokens "
                         f"{tuple(tokens.shape)}, got {got}")


@torch.no_grad()
def action_signal(net: WorldModel, batches: Iterable[tuple[torch.Tensor, ...]], stream: str = "actions"
                  ) -> dict[str, Any]:
    """Every statistic of the module doc over windows of tokens (b, T, n) int64, actions (b, T, l) (physical units)
    and, for stream "text", encoded captions (b, T, m, e) as a third element → a JSON-ready dict: per layer lists
    (heads inside), gradients, KL, the stream and the number of windows."""
    if stream not in STREAMS:
        raise ValueError(f"stream {stream!r}: expected one of {STREAMS}")
    net.eval()
    acc, windows, layout = Accumulator(), 0, None
    for tokens, actions, *rest in batches:
        text = rest[0] if rest else None
        check_window(net, tokens, actions, text, stream)
        layout = Layout(net.m, net.n, net.l, tokens.shape[1])
        kept, dropped = (conditions(net, actions, drop, text, stream) for drop in (False, True))
        streams = block_inputs(net, tokens, kept)
        attention_statistics(net, streams, layout, acc, stream)
        counterfactual_statistics(net, streams, block_inputs(net, tokens, dropped), layout, acc)
        prediction_kl(net, tokens, kept, dropped, acc)
        gradient_statistics(net, tokens, actions, layout, acc, stream, text)
        windows += tokens.shape[0]
    if layout is None:
        raise ValueError("action_signal: no windows given")
    return summarise(acc, len(net.transformer.blocks), windows, layout) | {"stream": stream}


def summarise(acc: Accumulator, depth: int, windows: int, layout: Layout) -> dict[str, Any]:
    def listed(name: str) -> list[float]:
        return [float(v) for v in acc.mean(name).flatten()]

    layers = [{"layer": i, "mass_all": listed(f"mass_all/{i}"), "mass_nearest": listed(f"mass_nearest/{i}"),
               "uniform_all": float(acc.mean(f"uniform_all/{i}")), "write_head": listed(f"write_head/{i}"),
               "write": float(acc.mean(f"write/{i}"))} for i in range(depth)]
    return {"windows": windows, "steps": layout.steps, "image_tokens": layout.n, "action_tokens": layout.l,
            "layers": layers,
            # index 0: the embedded input (where the action shortcut adds the actions); i ≥ 1: after block i − 1
            "counterfactual": [float(acc.mean(f"counterfactual/{i}")) for i in range(depth + 1)],
            "kl_nats": float(acc.mean("kl")),
            "grad_input": {kind: float(acc.mean(f"grad_input/{kind}")) for kind in ("actions", "image", "text")},
            "grad_param": {k.split("/")[1]: float(acc.mean(k)) for k in acc.sums if k.startswith("grad_param/")},
            "grad_relative": {k.split("/")[1]: float(acc.mean(k)) for k in acc.sums
                              if k.startswith("grad_relative/")}}


NEAREST = {"actions": "the previous step's actions", "text": "this step's caption"}
WRITE = {"actions": "actions' write", "text": "the text's write"}


def markdown(results: dict[str, Any], name: str) -> str:
    """One table per model: per layer, the head means and the strongest head."""
    stream = results.get("stream", "actions")
    lines = [f"**{name}** ({results['windows']} windows of {results['steps']} steps, {results['image_tokens']} image "
             f"tokens per step; stream: {stream})", "",
             f"| layer | attention on {stream} tokens (mean of heads / strongest head) | uniform share | on "
             f"{NEAREST[stream]} (mean / strongest) | {WRITE[stream]} ÷ residual | counterfactual share after the "
             "layer |",
             "|---|---|---|---|---|---|"]
    cf = results["counterfactual"]
    lines.append(f"| embedding | – | – | – | – | {cf[0]:.4f} |")
    for row in results["layers"]:
        mass, prev = row["mass_all"], row["mass_nearest"]
        lines.append(f"| {row['layer']} | {sum(mass) / len(mass):.4f} / {max(mass):.4f} | {row['uniform_all']:.4f} | "
                     f"{sum(prev) / len(prev):.4f} / {max(prev):.4f} | {row['write']:.4f} | "
                     f"{cf[row['layer'] + 1]:.4f} |")
    grad, rel = results["grad_input"], results["grad_relative"]
    lines += ["", f"- KL(p(·| {stream}) ‖ p(·| null {stream})) per image token: {results['kl_nats']:.4f} nats",
              f"- mean ‖∂L/∂x‖ per input position: actions {grad['actions']:.3e}, image {grad['image']:.3e}, text "
              f"{grad['text']:.3e} ({stream} ÷ image {grad[stream] / max(grad['image'], 1e-30):.2f})",
              "- ‖∂L/∂θ‖ ÷ ‖θ‖: " + ", ".join(f"{k} {v:.3e}" for k, v in rel.items())]
    return "\n".join(lines) + "\n"
