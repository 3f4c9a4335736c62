"""Prioritized replay of the agent's transitions (``buffer.priority``; Schaul et al., 2016).

Proportional prioritization: a stored transition ``i`` is drawn with probability
``P(i) = p_i / sum_j p_j``, ``p_i = (|delta_i| + eps) ** alpha`` where ``delta_i`` is its TD
error when it was last in a batch; a newly written transition gets the largest priority seen so
far, so each is drawn soon after it arrives. The loss weights each drawn item by
``w_i = (N P(i)) ** -beta`` (importance sampling; normalised by the batch's largest weight, and
TorchRL's ``DQNLoss`` takes the weighted mean ``sum w l / sum w``). ``alpha`` and ``beta`` stay
fixed over the run, as Dopamine's Rainbow sets them (0.5 and 0.5).

Why: the final weights of a uniform-replay run value its own late crash transitions at Q 11-31
against a target of -3 to -5, while the other transitions are fitted to a TD error under 2
(``docs/results/issue30/screens.md``, section 11): a transition written late is drawn about
``8 ln(T / s)`` times, too few to fit a rare event. Their TD errors are the batch's largest, so
prioritization draws them until they are fitted, and draws little of what is already fitted.

State: the priorities of the stored rows and the largest priority, saved and restored with the
buffer (``dumps`` / ``loads``), and torch's global generator for the draws, as TorchRL's
``RandomSampler``: a resumed run samples exactly what the uninterrupted one would.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.data.replay_buffers.samplers import Sampler
from torchrl.data.replay_buffers.storages import Storage

WEIGHT_KEY = "priority_weight"
"""Batch key of the importance weights (``DQNLoss``'s ``tensor_keys.priority_weight``)."""
TD_KEY = "td_error"
"""Batch key where ``DQNLoss`` writes each item's squared TD error (``tensor_keys.priority``)."""
INDEX_KEY = "index"
"""Batch key of each item's row in the agent storage (-1: a demo item, not prioritized)."""


class PrioritySampler(Sampler):
    """Proportional prioritized sampling over the rows of one storage.

    Args:
        capacity: rows of the storage (its ``max_size``).
        alpha: priority exponent (0 would be uniform; > 0 here).
        beta: importance-sampling exponent (0: no correction, 1: full).
        eps: added to ``|delta|`` so no stored transition has zero probability.
    """

    # Hand-written: TorchRL's PrioritizedSampler keeps its priorities in compiled segment trees
    # that do not load with the project's torch build (2.13); a cumulative sum over 1e5 rows
    # per batch is cheap next to an update (memrl.bench memory times it).
    def __init__(self, capacity: int, alpha: float, beta: float, eps: float = 1e-3) -> None:
        if not 0.0 < alpha <= 1.0:
            raise ValueError(f"priority alpha must be in (0, 1], got {alpha}")
        if not 0.0 <= beta <= 1.0:
            raise ValueError(f"priority beta must be in [0, 1], got {beta}")
        self.capacity, self.alpha, self.beta, self.eps = int(capacity), float(alpha), float(beta), float(eps)
        self._priority = torch.zeros(self.capacity, dtype=torch.float64)
        self._max = 1.0

    # ------------------------------------------------------------------ write side
    def extend(self, index: torch.Tensor) -> None:
        """New rows (or overwritten ones) get the largest priority so far."""
        self._priority[torch.as_tensor(index).reshape(-1).long().cpu()] = self._max

    def add(self, index: int) -> None:
        self.extend(torch.tensor([index]))

    def update_priority(self, index: int | torch.Tensor, priority: float | torch.Tensor, *,
                        storage: Storage | None = None) -> None:
        """Set rows ``index`` to ``(|delta| + eps) ** alpha`` of their TD errors ``priority``
        (``|delta|``, one per row; a row drawn twice keeps its last value)."""
        idx = torch.as_tensor(index).reshape(-1).long().cpu()
        delta = torch.as_tensor(priority, dtype=torch.float64).reshape(-1).cpu().abs()
        p = (delta + self.eps) ** self.alpha
        self._priority[idx] = p
        self._max = max(self._max, float(p.max())) if len(p) else self._max

    # ------------------------------------------------------------------ read side
    def sample(self, storage: Storage, batch_size: int) -> tuple[torch.Tensor, dict[str, Any]]:
        n = len(storage)
        if n == 0:
            raise RuntimeError("cannot sample from an empty buffer")
        cdf = self._priority[:n].cumsum(0)
        u = torch.rand(batch_size, dtype=torch.float64) * cdf[-1]
        index = torch.searchsorted(cdf, u, right=True).clamp_(max=n - 1)
        prob = self._priority[index] / cdf[-1]
        weight = (n * prob) ** -self.beta
        weight = (weight / weight.max()).to(torch.float32)
        return index, {WEIGHT_KEY: weight}

    # ------------------------------------------------------------------ state
    def _empty(self) -> None:
        self._priority.zero_()
        self._max = 1.0

    def state_dict(self) -> dict[str, Any]:
        return {"priority": self._priority.clone(), "max": self._max}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self._priority.copy_(state_dict["priority"])
        self._max = float(state_dict["max"])

    def dumps(self, path: str | Path) -> None:
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        torch.save(self._priority, path / "priority.pt")
        (path / "priority.json").write_text(json.dumps(
            {"max": self._max, "capacity": self.capacity, "alpha": self.alpha, "beta": self.beta}))

    def loads(self, path: str | Path) -> None:
        path = Path(path)
        meta = json.loads((path / "priority.json").read_text())
        if int(meta["capacity"]) != self.capacity:
            raise ValueError(f"priorities saved for {meta['capacity']} rows, this buffer has {self.capacity}")
        self._priority.copy_(torch.load(path / "priority.pt"))
        self._max = float(meta["max"])

    def __repr__(self) -> str:
        return f"{type(self).__name__}(capacity={self.capacity}, alpha={self.alpha}, beta={self.beta})"


def reprioritize(sampler: PrioritySampler, batch: TensorDictBase) -> None:
    """Give the agent rows of an updated ``batch`` their new TD errors as priorities.

    ``DQNLoss`` wrote each item's squared TD error into the batch (:data:`TD_KEY`); items whose
    :data:`INDEX_KEY` is negative are demos and keep none.
    """
    index = batch.get(INDEX_KEY).reshape(-1)
    delta = batch.get(TD_KEY).reshape(-1).to(torch.float64).sqrt()
    agent = index >= 0
    sampler.update_priority(index[agent], delta[agent])
