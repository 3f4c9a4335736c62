"""A few greedy episodes during training: the survival / goal scores as training goes on.

Its scenes come from their own seed domain (``periodic``): the same every time it runs
(less noise between points of the curve), and different from both the training episodes and
the final Table III scenes, so that looking at it does not tune on the test scenes.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from omegaconf import DictConfig, OmegaConf
from torch import nn

from memrl.evaluation.policies import GreedyActor
from memrl.evaluation.protocol import INITIAL_LANES, ProtocolConfig, protocol_env, scenario_seeds, score
from memrl.evaluation.runner import Job, run_jobs


@dataclass
class PeriodicEvalConfig:
    """The ``eval`` node of the train config."""

    every: int = 0
    """Training episodes between evaluations (0: off)."""
    episodes: int = 10
    """Episodes per initial-lane setting at each evaluation."""
    seed: int = 0
    """Base of the periodic scenes' seeds."""
    initial_lanes: list[str] = field(default_factory=lambda: list(INITIAL_LANES))
    """Initial-lane settings to evaluate."""
    batch: int = 10
    """Episodes stepped in lockstep (one Q-network forward for all)."""


PERIODIC_FIELDS = ("episode", "env_steps", "survival_random", "goal_random", "survival_non_goal",
                   "goal_non_goal", "return_random", "return_non_goal", "steps_random",
                   "steps_non_goal", "wall_s")
"""Columns of ``eval_periodic.csv`` in a run folder (scores per 100 episodes)."""

PERIODIC_CSV = "eval_periodic.csv"


def periodic_eval(qnet: nn.Module, env_cfg: Mapping[str, Any] | DictConfig, episodes: int = 10,
                  seed: int = 0, *, initial_lanes: Sequence[str] = INITIAL_LANES,
                  duration: int | None = None, batch: int = 10) -> dict[str, float]:
    """Greedy episodes of ``qnet`` in this process; returns the metrics of one CSV row.

    Args:
        qnet: the online Q-network (copied; the training one is left as it is).
        env_cfg: the training env config; the protocol's rules (0-5 constant-speed cars, the
            initial lane) are applied on top.
        episodes: episodes per initial-lane setting.
        seed: base of the scene seeds (domain ``periodic``).
        initial_lanes: settings to evaluate.
        duration: steps per episode (None: the env config's ``duration``).
        batch: episodes stepped together.

    Returns:
        ``survival_<lane>``, ``goal_<lane>`` (per 100 episodes), ``return_<lane>``,
        ``steps_<lane>`` (means) for each setting, and ``wall_s``.
    """
    env = OmegaConf.to_container(env_cfg, resolve=True) if isinstance(env_cfg, DictConfig) else dict(env_cfg)
    protocol = ProtocolConfig(episodes=episodes, seed=seed, initial_lanes=list(initial_lanes),
                              duration=int(duration or env.get("duration", 300)))  # type: ignore[union-attr]
    seeds = list(enumerate(scenario_seeds(seed, episodes, domain="periodic")))
    jobs = [Job(protocol_env(env, protocol, lane), lane, seeds) for lane in initial_lanes]  # type: ignore[arg-type]
    start = time.perf_counter()
    records = run_jobs(GreedyActor(qnet), jobs, workers=1, batch=batch).records  # type: ignore[arg-type]
    out: dict[str, float] = {}
    for lane in initial_lanes:
        s = score(r for r in records if r.initial_lane == lane)
        out.update({f"survival_{lane}": s.survival_score, f"goal_{lane}": s.goal_score,
                    f"return_{lane}": s.mean_return, f"steps_{lane}": s.mean_steps})
    out["wall_s"] = time.perf_counter() - start
    return out
