"""The typed ``eval`` node of the train config (periodic evaluation), without torch imports."""

from __future__ import annotations

from dataclasses import dataclass

from memrl.evaluation.protocol import INITIAL_LANES
from memrl.fields import spec


@dataclass
class PeriodicEvalConfig:
    """The ``eval`` node of the train config."""

    every: int = spec(0, ge=0)
    """Training episodes between evaluations (0: off)."""
    episodes: int = spec(10, ge=1)
    """Episodes per initial-lane setting at each evaluation."""
    seed: int = spec(0, ge=0)
    """Base of the periodic scenes' seeds."""
    initial_lanes: list[str] = spec(list(INITIAL_LANES), choices=INITIAL_LANES, nonempty=True)
    """Initial-lane settings to evaluate."""
    batch: int = spec(10, ge=1)
    """Episodes stepped in lockstep (one Q-network forward for all)."""
