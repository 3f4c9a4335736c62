"""Builds a stage of a mode (:mod:`memrl.modes`): its buffer, exploration and loss terms.

The stage's spec says what (the share its prior knowledge holds, its epsilon schedule, its loss
terms, its optimizer settings); this module turns that into TorchRL pieces: the buffer
(:mod:`memrl.data.buffers`), the exploration module (:mod:`memrl.dqn.exploration`) and the terms
(:mod:`memrl.losses`) the learner is started with. Nothing here names a mode.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from torchrl.modules import EGreedyModule

from memrl.data.buffers import PriorKnowledgeBuffer, agent_buffer, demo_buffer
from memrl.dqn.exploration import make_exploration
from memrl.dqn.stage1 import split_demos
from memrl.losses import LossTerm, td_term
from memrl.modes import HeadTD, StageSpec

EXPLORATION_OPTIONS = ("ez_mu", "ez_max_duration", "temperature_start", "temperature_end")


@dataclass
class Stage:
    """What a stage trains with."""

    spec: StageSpec
    buffer: Any
    explore: EGreedyModule | None
    """Epsilon-greedy of the acting policy (None: an offline stage, no env steps)."""
    terms: tuple[LossTerm, ...]
    """Its loss terms as the spec lists them, the value head's own TD term in ``HEAD_TD``'s place."""
    lr: float | None = None
    """Its own learning rate (None: the optimizer's)."""
    held_out: TensorDictBase | None = None
    """Offline stage: demos kept out of its buffer to measure agreement."""
    updates_per_round: int = 1
    """Gradient updates per round (online stage; an offline stage's count is its stop rule's)."""

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def offline(self) -> bool:
        return self.spec.offline


@dataclass(frozen=True)
class StageInputs:
    """The train config's nodes a stage is built from, and nothing else of it."""

    mode: Any
    """The ``mode`` node: the only thing a stage declaration reads (:class:`StageSpec`)."""
    agent: Any
    """The ``agent`` node (:class:`memrl.dqn.config.AgentConfig`)."""
    buffer: Any
    """The ``buffer`` node (:class:`memrl.dqn.config.BufferConfig`)."""
    network: Any
    """The ``network`` node: whose TD term stands in for :data:`memrl.modes.HEAD_TD`."""
    seed: int
    """The run's seed (an offline stage's held-out split)."""
    frame_stride: int = 1
    """``env.frame_stride``: env steps between stacked frames (the n-step windows' stride)."""

    @classmethod
    def of(cls, cfg: DictConfig) -> StageInputs:
        """The nodes of a train config."""
        return cls(cfg.mode, cfg.agent, cfg.buffer, cfg.network, int(cfg.seed), int(cfg.env.frame_stride))


def build_stage(spec: StageSpec, nodes: StageInputs, demos: TensorDictBase | None, num_envs: int,
                device: torch.device) -> Stage:
    """Build stage ``spec`` from the train config's ``nodes``.

    Args:
        spec: the stage's declaration.
        nodes: the train config's nodes it reads.
        demos: the prior knowledge (modes that read it).
        num_envs: envs writing into the buffer (its frame ring has one stream per env).
        device: where the buffer lives.
    """
    a, b, m = nodes.agent, nodes.buffer, nodes.mode
    capacity, batch = int(b.capacity), int(a.batch_size)
    compact = bool(b.compact)  # each frame stored once
    store: dict[str, Any] = {"compact": compact, "streams": num_envs, "device": device,
                             "crash_share": float(b.crash_share), "priority": float(b.priority),
                             "priority_beta": float(b.priority_beta)}

    def own(value: Any, default: Any) -> Any:  # a stage's own value, else the agent's
        return default if value is None else value

    # memrl.data.nstep
    nstep = {"n_step": int(own(spec.n_step(m), a.n_step)), "gamma": float(a.gamma)}
    if nodes.frame_stride != 1:  # frames between stacked frames
        nstep["stride"] = nodes.frame_stride
    # the stage's terms, HEAD_TD replaced by the value head's own TD term
    terms = tuple(td_term(a, nodes.network) if isinstance(t, HeadTD) else t for t in spec.terms(m))
    lr = spec.lr(m)
    lr = None if lr is None else float(lr)
    if spec.offline:
        assert demos is not None
        train, held_out = split_demos(demos, float(m[spec.settings].holdout_fraction), nodes.seed,
                                      keep_order=nstep["n_step"] > 1)
        return Stage(spec, demo_buffer(train, batch, compact=compact, device=device, **nstep), None, terms,
                     lr, held_out.to(device))
    schedule = own(spec.exploration(m), (a.eps_start, a.eps_end, a.eps_decay_frames))
    explore = make_exploration(*schedule, kind=str(a.exploration), num_envs=num_envs,
                               **{k: a[k] for k in EXPLORATION_OPTIONS})
    explore.to(device)
    share = float(spec.demo_share(m))
    if share > 0:
        assert demos is not None
        buffer: Any = PriorKnowledgeBuffer(demos, capacity, share, batch, sampling=str(m.sampling),
                                           **store, **nstep)
    else:
        buffer = agent_buffer(capacity, batch, **store, **nstep)
    return Stage(spec, buffer, explore, terms, lr, updates_per_round=int(own(spec.updates_per_round(m),
                                                                             a.updates_per_round)))
