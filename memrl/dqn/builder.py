"""The mode builder: each training stage's buffer, exploration and loss settings, and its successor.

Stages: ``default`` (plain double DQN), ``A`` (prior knowledge holds ``demo_fraction`` of the
buffer, stratified batches), ``B1`` (mode B stage 1: prior knowledge only, + large-margin loss,
no env steps) and ``B2`` (mode B stage 2: from B1's weights, trains as Default; with
``mode.stage2.demo_fraction > 0`` the prior knowledge stays in its buffer as in mode A).
A and B2 add the large-margin loss on their batches' demos when ``mode.margin_weight`` /
``mode.stage2.margin_weight`` > 0.
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
from memrl.dqn.learner import Learner
from memrl.dqn.stage1 import split_demos

FIRST_STAGE = {"default": "default", "A": "A", "B": "B1"}
"""The stage a run of each mode starts in."""
NEXT_STAGE = {"B1": "B2"}
EXPLORATION_OPTIONS = ("ez_mu", "ez_max_duration", "temperature_start", "temperature_end")
"""The stage that follows a finished offline stage."""


@dataclass
class Stage:
    """What a stage trains with."""

    name: str
    buffer: Any
    explore: EGreedyModule | None
    """Epsilon-greedy of the acting policy (None: an offline stage, no env steps)."""
    held_out: TensorDictBase | None = None
    """Offline stage: demos kept out of its buffer to measure agreement."""

    @property
    def offline(self) -> bool:
        return self.explore is None


def build_stage(name: str, cfg: DictConfig, learner: Learner, demos: TensorDictBase | None,
                num_envs: int, device: torch.device) -> Stage:
    """Build stage ``name`` of the run ``cfg`` and set the learner's loss for it.

    Args:
        name: ``default``, ``A``, ``B1`` or ``B2``.
        cfg: the train config.
        learner: its margin loss weight (and, in B1, learning rate) is set here.
        demos: the prior knowledge (modes A and B).
        num_envs: envs writing into the buffer (its frame ring has one stream per env).
        device: where the buffer lives.
    """
    a, m = cfg.agent, cfg.mode
    capacity, batch = int(cfg.buffer.capacity), int(a.batch_size)
    compact = bool(cfg.buffer.get("compact", True))  # each frame stored once
    store: dict[str, Any] = {"compact": compact, "streams": num_envs, "device": device}
    nstep = {"n_step": int(a.get("n_step", 1)), "gamma": float(a.gamma)}  # memrl.data.nstep
    if int(cfg.env.get("frame_stride", 1)) != 1:  # frames between stacked frames
        nstep["stride"] = int(cfg.env.frame_stride)
    learner.margin_weight = 0.0
    if name == "B1":
        assert demos is not None
        learner.margin_weight, learner.margin = float(m.stage1.margin_weight), float(m.stage1.margin)
        if m.stage1.lr is not None:  # a resumed run gets the same from the optimizer state
            learner.set_lr(float(m.stage1.lr))
        train, held_out = split_demos(demos, float(m.stage1.holdout_fraction), int(cfg.seed),
                                      keep_order=nstep["n_step"] > 1)
        return Stage(name, demo_buffer(train, batch, compact=compact, device=device, **nstep), None,
                     held_out.to(device))
    schedule = (m.stage2.eps_start, m.stage2.eps_end, m.stage2.eps_decay_frames) if name == "B2" \
        else (a.eps_start, a.eps_end, a.eps_decay_frames)
    explore = make_exploration(*schedule, kind=str(a.get("exploration", "epsilon")),
                               num_envs=num_envs,
                               **{k: a[k] for k in EXPLORATION_OPTIONS if a.get(k) is not None})
    explore.to(device)
    share = float(m.demo_fraction) if name == "A" else \
        float(m.stage2.get("demo_fraction", 0.0)) if name == "B2" else 0.0
    if share > 0:
        assert demos is not None
        learner.margin_weight = float(m.get("margin_weight", 0.0)) if name == "A" else \
            float(m.stage2.get("margin_weight", 0.0))
        learner.margin = float(m.stage1.margin)
        buffer: Any = PriorKnowledgeBuffer(demos, capacity, share, batch, sampling=str(m.sampling),
                                           **store, **nstep)
    else:
        buffer = agent_buffer(capacity, batch, **store, **nstep)
    return Stage(name, buffer, explore)
