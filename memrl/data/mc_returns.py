"""Monte-Carlo returns of stored transitions (prior knowledge, recorded episodes), for
calibration checks of Q-values against what the recorded policy actually got (Cal-QL's
diagnosis, Nakamoto et al. 2023: an offline stage's Q(s, a_demo) against the demos' returns).

Row ``t + 1`` continues row ``t`` when ``t`` is not done and its ``("next", "pixels")`` are row
``t + 1``'s ``pixels`` (datasets store episodes in order, but recipes may cut an episode's tail
or noise steps: content, not position, tells). Along each such chain, ``G_t = r_t + gamma
G_(t+1)``; at a chain's end the sum stops. A return is *known* where the chain ends in a
termination (a crash: nothing follows) or at least ``horizon`` steps later (what the cut
misses weighs at most ``gamma^horizon`` of a return). The sums are TorchRL's ``reward2go`` with
the chains' ends as its episode ends (it drops terms below 1e-7 of a step's reward); what is
written here is where a chain ends, which TorchRL reads from done flags alone.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.objectives.value.functional import reward2go

CHUNK = 1024
"""Rows compared at once (two uint8 stacks of 28 KB each per row)."""


def continues(td: TensorDictBase) -> torch.Tensor:
    """``[N]`` bool: row ``t + 1`` continues row ``t`` (the last row: False)."""
    n = td.shape[0]
    out = torch.zeros(n, dtype=torch.bool)
    done = td.get(("next", "done")).reshape(n)
    for lo in range(0, n - 1, CHUNK):
        hi = min(lo + CHUNK, n - 1)
        nxt = td.get(("next", "pixels"))[lo:hi]
        following = td.get("pixels")[lo + 1:hi + 1]
        out[lo:hi] = (nxt == following).flatten(1).all(1) & ~done[lo:hi]
    return out


def mc_returns(td: TensorDictBase, gamma: float, horizon: int = 100) -> tuple[torch.Tensor, torch.Tensor]:
    """``(G [N] float64, known [N] bool)`` of the rows of ``td`` (module docstring)."""
    n = td.shape[0]
    end = ~continues(td)  # [N] the last row of its chain
    chain = torch.cat([end.new_zeros(1), end[:-1]]).long().cumsum(0)  # [N] each row's chain
    last = torch.nonzero(end).reshape(-1)[chain]  # [N] the last row of each row's chain
    terminated = td.get(("next", "terminated")).reshape(n)
    known = terminated[last] | (last - torch.arange(n) >= horizon)
    reward = td.get(("next", "reward")).reshape(n, 1).to(torch.float64)
    return reward2go(reward, end.reshape(n, 1), gamma).reshape(n), known
