"""HL-Gauss (Farebrother et al., 2024, "Stop Regressing"): the categorical head of
:mod:`memrl.modules.categorical` over ``atoms`` equal bins from ``v_min`` to ``v_max``, trained
by cross-entropy on the histogram that a Gaussian of width ``sigma`` bins, centred on the
scalar double-DQN target, puts in each bin (``network=hlgauss``). The Q-value is the
expectation over the bin centres; the TD error for prioritized replay is that of the
expected values.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDictBase

from memrl.fields import spec
from memrl.modules.categorical import (
    CategoricalConfig,
    CategoricalQNetwork,
    bootstrap,
    refuse_advantage_learning,
    taken,
)


@dataclass
class HLGaussConfig(CategoricalConfig):
    """An HL-Gauss value head (``network=hlgauss``): ``atoms`` bins, a Gaussian of ``sigma`` bins."""

    sigma: float = spec(0.75, gt=0)
    """Standard deviation of the target Gaussian [bin widths] (the paper's sigma / zeta: 0.75)."""


class HLGaussQNetwork(CategoricalQNetwork):
    """Table I's trunk with ``atoms`` logits per action over equal bins; Q = sum_i p_i c_i."""

    config_schema = HLGaussConfig

    def __init__(self, *args: Any, sigma: float = 0.75, **kwargs: Any) -> None:
        if not sigma > 0:
            raise ValueError(f"HLGaussQNetwork: need sigma > 0, got {sigma}")
        self.sigma = float(sigma)
        super().__init__(*args, **kwargs)
        self.arch["sigma"] = self.sigma

    def support_values(self) -> torch.Tensor:
        """The bin centres ``[atoms]``."""
        width = (self.v_max - self.v_min) / self.atoms
        return self.v_min + width * (torch.arange(self.atoms, dtype=torch.float32) + 0.5)

    def conversion_width(self) -> float:
        """``sigma`` bin widths: a converted scalar head's distribution has the targets' shape."""
        return self.sigma * (self.v_max - self.v_min) / self.atoms

    @classmethod
    def td_term(cls, agent: Any) -> HLGaussTerm:
        refuse_advantage_learning(cls, agent)
        return HLGaussTerm(gamma=float(agent.gamma))


def gauss_histogram(targets: torch.Tensor, v_min: float, v_max: float, bins: int,
                    sigma: float) -> torch.Tensor:
    """``[B, bins]``: the mass a Gaussian of standard deviation ``sigma`` [return units] centred
    on each target (clipped into ``[v_min, v_max]``) puts in each bin, renormalised to the
    range's mass: bin i gets ``Phi((e_{i+1} - y) / sigma) - Phi((e_i - y) / sigma)``, divided
    by ``Phi((e_K - y) / sigma) - Phi((e_0 - y) / sigma)`` (``e``: the bins' edges)."""
    edges = torch.linspace(v_min, v_max, bins + 1, device=targets.device, dtype=torch.float32)
    y = targets.to(torch.float32).clamp(v_min, v_max)[:, None]
    cdf = 0.5 * (1.0 + torch.erf((edges[None, :] - y) / (sigma * math.sqrt(2.0))))
    return (cdf[:, 1:] - cdf[:, :-1]) / (cdf[:, -1:] - cdf[:, :1])


@dataclass(frozen=True)
class HLGaussTerm:
    """HL-Gauss's TD term: cross-entropy between the Gaussian histogram of the scalar target
    ``r + gamma^m Q_target(s', argmax_a Q_online(s', a))`` (``r`` after a crash) and the online
    distribution of ``(s, a)``, mean over the batch."""

    gamma: float
    weight: float = 1.0
    name: str = "hlgauss"

    def __call__(self, batch: TensorDictBase, q: Any) -> torch.Tensor:
        net = q.qnet
        log_p, q_sa = taken(batch, q)
        with torch.no_grad():
            y = self.scalar_target(batch, q)
            width = (net.v_max - net.v_min) / net.atoms
            target = gauss_histogram(y, net.v_min, net.v_max, net.atoms, net.sigma * width)
            q.td_error = (y - q_sa).pow(2)[:, None]
        return self.weight * -(target * log_p).sum(-1).mean()

    @torch.no_grad()
    def scalar_target(self, batch: TensorDictBase, q: Any) -> torch.Tensor:
        """The double-DQN target ``[B]`` on the expected values."""
        next_pixels = batch.get(("next", "pixels"))
        a_star = q.greedy(next_pixels)
        nxt = q.target(next_pixels)["q"].gather(-1, a_star[:, None]).squeeze(-1)
        reward, discount = bootstrap(batch, self.gamma)
        return reward + discount * nxt
