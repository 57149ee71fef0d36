"""GAIA-1 world-model rollouts: futures of image tokens from context frames, text and actions (GAIA-1 §5.1)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from gaia_app.diffusion.ar_sampling import AutoregressiveSampler, SamplingSession
from gaia_app.diffusion.guidance import ClassifierFreeGuidance
from gaia_app.models.gaia1.world_model import STREAMS, Conditions, WorldModel


@dataclass
class RolloutOutput:
    """tokens: (b·futures, t0 + f, n) int64, futures of one example adjacent; context_frames: t0."""

    tokens: torch.Tensor
    context_frames: int


def repeat_futures(x: torch.Tensor | None, futures: int) -> torch.Tensor | None:
    """(b, ...) → (b·futures, ...), each example's copies adjacent."""
    return None if x is None else x.repeat_interleave(futures, dim=0)


class WorldModelRolloutPipeline:
    """Rolls out futures with the KV-cached sampler, optionally guided (eq. 3) or negatively prompted.

    Args:
        net: the world model. sampler: AutoregressiveSampler. guidance: ClassifierFreeGuidance or None.
        guided_streams: streams the unconditioned stream drops (paper: no conditioning at all).
    """

    def __init__(self, net: WorldModel, sampler: AutoregressiveSampler, guidance: ClassifierFreeGuidance | None = None,
                 guided_streams: Sequence[str] = STREAMS):
        self.net, self.sampler, self.guidance = net, sampler, guidance
        self.guided_streams = tuple(guided_streams)

    def conditions(self, batch: int, steps: int, text: torch.Tensor | None, actions: torch.Tensor | None,
                   drop: Sequence[str] = ()) -> Conditions:
        """Every given stream kept (whatever the net's train/eval mode), except those in `drop`."""
        force = {"text": text is None or "text" in drop, "actions": actions is None or "actions" in drop}
        return self.net.conditioner(batch, steps, text, actions, force)

    @torch.no_grad()
    def __call__(self, context: torch.Tensor, frames: int, text: torch.Tensor | None = None,
                 actions: torch.Tensor | None = None, negative_text: torch.Tensor | None = None,
                 num_futures: int = 1, generator: torch.Generator | None = None, lead: int = 0,
                 noise_groups: torch.Tensor | None = None) -> RolloutOutput:
        """context (b, t0, n) int64; text, negative_text: (b, lead + t0 + f, m, e) encoder outputs; actions:
        (b, lead + t0 + f, 2). noise_groups (b,) int64: examples with equal values (e.g. one context under several
        commands) share their sampling noise, future by future (counterfactual futures, ar_sampling.shared_gumbel);
        None: every future draws its own.

        Several futures per example are sampled in one batch (`num_futures`). The first `lead` steps of the streams
        precede the context and only inform the conditions (with action deltas, the change of the context's first
        action): a window cut from a longer rollout is then conditioned exactly as in that rollout.
        """
        steps = lead + context.shape[1] + frames
        context, text, actions, negative_text = (repeat_futures(x, num_futures)
                                                 for x in (context, text, actions, negative_text))
        cond, uncond = self.streams(context.shape[0], steps, text, actions, negative_text, lead)
        groups = None if noise_groups is None else future_groups(noise_groups, num_futures)
        tokens = self.sampler(self.net, context, cond, uncond, frames, self.rollout_guidance(text), generator, groups)
        return RolloutOutput(tokens, context.shape[1])

    def streams(self, batch: int, steps: int, text: torch.Tensor | None, actions: torch.Tensor | None,
                negative_text: torch.Tensor | None = None, lead: int = 0,
                guided: bool | None = None) -> tuple[Conditions, Conditions | None]:
        """The conditioned stream and, when guided (by default: when the pipeline has guidance), the unconditioned
        (or negative-prompt) one, for steps lead..steps − 1 of the given (b, steps, ...) streams (the first `lead`
        only inform action deltas)."""
        guided = self.guidance is not None if guided is None else guided
        cond = self.conditions(batch, steps, text, actions)
        uncond = None
        if guided and negative_text is not None:  # negative prompting (GAIA-1 §5.1)
            uncond = self.conditions(batch, steps, negative_text, actions)
        elif guided:
            uncond = self.conditions(batch, steps, text, actions, drop=self.guided_streams)
        if lead:
            cond, uncond = cond.steps(lead, steps), None if uncond is None else uncond.steps(lead, steps)
        return cond, uncond

    def rollout_guidance(self, text: torch.Tensor | None) -> ClassifierFreeGuidance | None:
        """The guidance of one rollout (text_scale when prompted), or None."""
        return None if self.guidance is None else self.guidance.for_rollout(prompted=text is not None)

    @torch.no_grad()
    def session(self, context: torch.Tensor, steps: int, text: torch.Tensor | None, actions: torch.Tensor | None,
                generator: torch.Generator | None = None, negative_text: torch.Tensor | None = None,
                guidance: ClassifierFreeGuidance | None | str = "pipeline") -> SamplingSession:
        """A rollout kept open for a closed loop: context (b, t0, n) int64 and the first `steps` (≥ t0) steps of its
        text (b, steps, m, e) and actions (b, steps, 2); `extend_session` appends further steps' conditions and
        `next_frame` samples one step at a time. guidance: "pipeline" (the pipeline's, its text scale when
        prompted), another ClassifierFreeGuidance, or None (unguided); chosen once for the whole session."""
        guidance = self.rollout_guidance(text) if guidance == "pipeline" else guidance
        cond, uncond = self.streams(context.shape[0], steps, text, actions, negative_text, guided=guidance is not None)
        return self.sampler.session(self.net, context, cond, uncond, guidance, generator,
                                    given_streams(text, actions, negative_text))

    @torch.no_grad()
    def extend_session(self, session: SamplingSession, actions: torch.Tensor, text: torch.Tensor | None = None,
                       negative_text: torch.Tensor | None = None, lead: int = 1) -> None:
        """Append steps to `session`: actions (b, lead + k, 2) and text (b, lead + k, m, e) whose first `lead` steps
        are those before the new ones (their actions give the first new step its action delta, as an open-loop
        rollout has it). The streams must be those the session was opened with."""
        given = given_streams(text, actions, negative_text)
        if given != session.given:
            raise ValueError(f"the session was opened with streams {session.given}; these steps bring {given}")
        session.extend(*self.streams(session.tokens.shape[0], actions.shape[1], text, actions, negative_text, lead,
                                     guided=session.guidance is not None))


def future_groups(groups: torch.Tensor, futures: int) -> torch.Tensor:
    """Noise groups (b,) of examples → (b·futures,) of their futures: the k-th futures of one group share noise,
    the futures of one example do not."""
    return groups.repeat_interleave(futures) * futures + torch.arange(futures, device=groups.device).repeat(len(groups))


def given_streams(text: torch.Tensor | None, actions: torch.Tensor | None,
                  negative_text: torch.Tensor | None) -> tuple[str, ...]:
    """Names of the condition streams given."""
    return tuple(name for name, x in (("text", text), ("actions", actions), ("negative", negative_text))
                 if x is not None)
