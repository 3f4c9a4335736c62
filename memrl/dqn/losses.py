"""Loss terms of the learner: each a small object with its weight from config, summed by the stage.

A stage lists its terms (:mod:`memrl.modes`); the learner is built with them and adds them
up (:meth:`memrl.dqn.learner.Learner.loss`). A new term is one class here with a ``__call__``
that takes the batch and the learner's pieces, and one line in the stage that uses it
(``docs/extending.md``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import torch
from tensordict import TensorDictBase
from torch import nn


class LossTerm(Protocol):
    """One weighted part of a stage's loss."""

    name: str

    def __call__(self, batch: TensorDictBase, loss_module: nn.Module, qnet: nn.Module,
                 q_online: torch.Tensor | None = None) -> torch.Tensor | None:
        """The term's weighted value on ``batch`` (differentiable); None where it does not
        apply to this batch (adds nothing, not even a zero). ``q_online``: the online
        Q-values of the whole batch's ``pixels`` as an earlier term computed them (with their
        gradient graph), None when none did."""


@dataclass(frozen=True)
class TDTerm:
    """Eq. (1): the mean of 1/2 (r + gamma^m Q_target(s', argmax_a Q(s', a)) - Q(s, a))^2, no
    bootstrap on terminated transitions (TorchRL's double ``DQNLoss``; its ``l2`` distance has
    no 1/2; ``m`` is the batch's ``steps_to_next_obs`` where n-step returns give one, else 1)."""

    weight: float = 1.0
    name: str = "td"

    def __call__(self, batch: TensorDictBase, loss_module: nn.Module, qnet: nn.Module,
                 q_online: torch.Tensor | None = None) -> torch.Tensor:
        return self.weight * 0.5 * loss_module(batch)["loss"]


@dataclass(frozen=True)
class MarginTerm:
    """DQfD's large-margin loss on the batch's demo items (Hester et al., 2018):
    max_a [Q(s, a) + margin * (a != a_demo)] - Q(s, a_demo), which makes the greedy action
    reproduce the demonstrations. Nothing for a batch without demo items."""

    weight: float
    margin: float = 0.8
    """[Q units] by which the demo action must beat every other action."""
    name: str = "margin"

    def __call__(self, batch: TensorDictBase, loss_module: nn.Module, qnet: nn.Module,
                 q_online: torch.Tensor | None = None) -> torch.Tensor | None:
        if "is_demo" not in batch.keys():
            return None
        demo = batch["is_demo"].reshape(-1)
        if not bool(demo.any()):
            return None
        # A batch of demos only (mode B's stage 1): the TD term's forward of the same pixels
        # serves, one forward and backward instead of two; else a forward of the demo rows.
        q = q_online if q_online is not None and bool(demo.all()) else qnet(batch["pixels"][demo])
        a = batch["action"][demo].reshape(-1, 1)
        margins = torch.full_like(q, self.margin).scatter_(-1, a, 0.0)
        excess = (q + margins).max(-1).values - q.gather(-1, a).squeeze(-1)
        return self.weight * excess.mean()


def margin_terms(weight: float, margin: float) -> list[LossTerm]:
    """The margin term when its weight is positive, else none (eq. (1) alone)."""
    return [MarginTerm(float(weight), float(margin))] if weight > 0 else []
