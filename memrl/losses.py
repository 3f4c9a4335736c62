"""Loss terms of the learner: each a small object with its weight from config, summed by the stage.

A stage lists its terms (:mod:`memrl.modes`); the learner is built with them and adds them
up (:meth:`memrl.dqn.learner.Learner.loss`). A new term is one class here with a ``__call__``
that takes the batch and the learner's pieces, and one line in the stage that uses it
(``docs/extending.md``). The terms sit beside the modes that name them, below the trainer
that sums them (``tests/test_import_cycles.py``: the layer order).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn

from memrl.data.priority_sampler import TD_KEY


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
    no 1/2; ``m`` is the batch's ``steps_to_next_obs`` where n-step returns give one, else 1).

    With ``advantage`` = alpha > 0 the target is advantage learning's (Bellemare et al., 2016):
    less alpha (max_b Q_target(s, b) - Q_target(s, a)), which leaves the greedy action's value
    as it is and multiplies the action gap by 1 / (1 - alpha)."""

    weight: float = 1.0
    advantage: float = 0.0
    """Advantage learning's alpha in [0, 1) (``agent.advantage_learning``); 0: eq. (1)."""
    name: str = "td"

    def __call__(self, batch: TensorDictBase, loss_module: nn.Module, qnet: nn.Module,
                 q_online: torch.Tensor | None = None) -> torch.Tensor:
        if self.advantage == 0:
            return self.weight * 0.5 * loss_module(batch)["loss"]
        # DQNLoss has no advantage-learning target: its reward is lowered by the correction
        # instead (the target is reward + bootstrap), on a copy that leaves the batch as it is.
        lowered = batch.clone(False)
        lowered.set("next", batch.get("next").clone(False))
        reward = batch.get(("next", "reward"))
        gap = self.advantage * target_action_gap(batch, loss_module)
        lowered.set(("next", "reward"), reward - gap.reshape(reward.shape).to(reward.dtype))
        loss = loss_module(lowered)["loss"]
        if TD_KEY in lowered.keys():  # the TD errors, for prioritized replay
            batch.set(TD_KEY, lowered.get(TD_KEY))
        return self.weight * 0.5 * loss


def td_term(agent: Any) -> TDTerm:
    """Eq. (1)'s term as the ``agent`` config sets it (``agent.advantage_learning``)."""
    return TDTerm(advantage=float(agent.advantage_learning))


@torch.no_grad()
def target_action_gap(batch: TensorDictBase, loss_module: nn.Module) -> torch.Tensor:
    """``max_b Q_target(s, b) - Q_target(s, a)`` per item ``[B]`` (>= 0; 0 for the greedy action),
    the target network's Q of the batch's own ``pixels`` and ``action``."""
    actor = loss_module.value_network
    with loss_module.target_value_network_params.to_module(actor, preserve_module_state=False):
        q = actor(TensorDict({"pixels": batch.get("pixels")}, batch.batch_size))["action_value"]
    a = batch.get("action").reshape(-1, 1).long()
    q = q.reshape(a.shape[0], -1)
    return q.max(-1).values - q.gather(-1, a).squeeze(-1)


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
