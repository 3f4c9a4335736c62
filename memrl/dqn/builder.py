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
        return self.explore is None


def build_stage(spec: StageSpec, cfg: DictConfig, demos: TensorDictBase | None, num_envs: int,
                device: torch.device) -> Stage:
    """Build stage ``spec`` of the run ``cfg``.

    Args:
        spec: the stage's declaration.
        cfg: the train config.
        demos: the prior knowledge (modes that read it).
        num_envs: envs writing into the buffer (its frame ring has one stream per env).
        device: where the buffer lives.
    """
    a = cfg.agent
    capacity, batch = int(cfg.buffer.capacity), int(a.batch_size)
    compact = bool(cfg.buffer.compact)  # each frame stored once
    store: dict[str, Any] = {"compact": compact, "streams": num_envs, "device": device,
                             "crash_share": float(cfg.buffer.crash_share),
                             "priority": float(cfg.buffer.priority),
                             "priority_beta": float(cfg.buffer.priority_beta)}
    n_step = spec.n_step(cfg)
    # memrl.data.nstep
    nstep = {"n_step": int(a.n_step if n_step is None else n_step), "gamma": float(a.gamma)}
    if int(cfg.env.frame_stride) != 1:  # frames between stacked frames
        nstep["stride"] = int(cfg.env.frame_stride)
    # the stage's terms, HEAD_TD replaced by the value head's own TD term
    terms = tuple(td_term(a, cfg.network) if isinstance(t, HeadTD) else t for t in spec.terms(cfg))
    lr = spec.lr(cfg)
    lr = None if lr is None else float(lr)
    share = float(spec.demo_share(cfg))
    if spec.offline(cfg):
        assert demos is not None
        train, held_out = split_demos(demos, float(cfg.mode[spec.settings].holdout_fraction), int(cfg.seed),
                                      keep_order=nstep["n_step"] > 1)
        return Stage(spec, demo_buffer(train, batch, compact=compact, device=device, **nstep), None, terms,
                     lr, held_out.to(device))
    per_round = spec.updates_per_round(cfg)
    per_round = int(a.updates_per_round if per_round is None else per_round)
    explore = make_exploration(*spec.exploration(cfg), kind=str(a.exploration), num_envs=num_envs,
                               **{k: a[k] for k in EXPLORATION_OPTIONS})
    explore.to(device)
    if share > 0:
        assert demos is not None
        buffer: Any = PriorKnowledgeBuffer(demos, capacity, share, batch, sampling=str(cfg.mode.sampling),
                                           **store, **nstep)
    else:
        buffer = agent_buffer(capacity, batch, **store, **nstep)
    return Stage(spec, buffer, explore, terms, lr, updates_per_round=per_round)
