"""The typed ``eval`` node of the train config (periodic evaluation), without torch imports."""

from __future__ import annotations

from dataclasses import dataclass

from memrl.evaluation.protocol import INITIAL_LANES
from memrl.fields import SEED_MAX, spec

UNITS = ("episodes", "env_steps")
"""What ``eval.every`` counts."""


@dataclass
class PeriodicEvalConfig:
    """The ``eval`` node of the train config."""

    every: int = spec(0, ge=0)
    """Training episodes (``unit: episodes``) or env steps (``unit: env_steps``) between
    evaluations (0: off)."""
    unit: str = spec("episodes", choices=UNITS)
    """What ``every`` counts. ``env_steps`` puts every seed's points at the same env steps
    (mode B's long episodes give few points per episode count); with N envs a point comes at
    the first step that crosses a multiple of ``every``, so its ``env_steps`` may pass it by
    less than one collection round."""
    episodes: int = spec(10, ge=1)
    """Episodes per initial-lane setting at each evaluation."""
    seed: int = spec(0, ge=0, le=SEED_MAX)
    """Base of the periodic scenes' seeds."""
    initial_lanes: list[str] = spec(list(INITIAL_LANES), choices=INITIAL_LANES, nonempty=True)
    """Initial-lane settings to evaluate."""
    batch: int = spec(10, ge=1)
    """Episodes stepped in lockstep (one Q-network forward for all)."""
