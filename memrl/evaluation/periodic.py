"""A few greedy episodes during training: the survival / goal scores as training goes on.

Its scenes come from their own seed domain (``periodic``): the same every time it runs
(less noise between points of the curve), and different from both the training episodes and
the final Table III scenes, so that looking at it does not tune on the test scenes.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from torch import nn

from memrl.csv_table import CsvTable
from memrl.envs.config import LaneChangeConfig
from memrl.evaluation.jobs import module_device
from memrl.evaluation.periodic_config import PeriodicEvalConfig
from memrl.evaluation.policies import GreedyActor
from memrl.evaluation.protocol import INITIAL_LANES, ProtocolConfig, protocol_env, scenario_seeds, score
from memrl.evaluation.runner import Job, run_jobs

PERIODIC_FIELDS = ("episode", "env_steps", "survival_random", "goal_random", "survival_non_goal",
                   "goal_non_goal", "return_random", "return_non_goal", "steps_random",
                   "steps_non_goal", "wall_s")
"""Columns of ``eval_periodic.csv`` in a run folder (scores per 100 episodes)."""

PERIODIC_CSV = "eval_periodic.csv"


def periodic_eval(qnet: nn.Module, env_cfg: Mapping[str, Any] | DictConfig, episodes: int = 10,
                  seed: int = 0, *, initial_lanes: Sequence[str] = INITIAL_LANES,
                  duration: int | None = None, batch: int = 10,
                  device: torch.device | str | None = None) -> dict[str, float]:
    """Greedy episodes of ``qnet`` in this process; returns the metrics of one CSV row.

    Args:
        qnet: the online Q-network (copied; the training one is left as it is).
        env_cfg: the training env config; the protocol's rules (0-5 constant-speed cars, the
            initial lane) are applied on top.
        episodes: episodes per initial-lane setting.
        seed: base of the scene seeds (domain ``periodic``).
        initial_lanes: settings to evaluate.
        duration: steps per episode (None: the env config's ``duration``).
        batch: episodes stepped together on gym envs (the greedy network runs on the batched
            engine instead, all episodes at once).
        device: where the engine and the network copy run (None: the network's device).

    Returns:
        ``survival_<lane>``, ``goal_<lane>`` (per 100 episodes), ``return_<lane>``,
        ``steps_<lane>`` (means) for each setting, and ``wall_s``.
    """
    env = OmegaConf.to_container(env_cfg, resolve=True) if isinstance(env_cfg, DictConfig) else dict(env_cfg)
    protocol = ProtocolConfig(episodes=episodes, seed=seed, initial_lanes=list(initial_lanes),
                              duration=int(duration or env.get("duration", LaneChangeConfig.duration)))  # type: ignore[union-attr]
    seeds = list(enumerate(scenario_seeds(seed, episodes, domain="periodic")))
    jobs = [Job(protocol_env(env, protocol, lane), lane, seeds) for lane in initial_lanes]  # type: ignore[arg-type]
    start = time.perf_counter()
    device = device if device is not None else module_device(qnet)
    records = run_jobs(GreedyActor(qnet), jobs, workers=1, batch=batch,  # type: ignore[arg-type]
                       device=device).records
    out: dict[str, float] = {}
    for lane in initial_lanes:
        s = score(r for r in records if r.initial_lane == lane)
        out.update({f"survival_{lane}": s.survival_score, f"goal_{lane}": s.goal_score,
                    f"return_{lane}": s.mean_return, f"steps_{lane}": s.mean_steps})
    out["wall_s"] = time.perf_counter() - start
    return out


class PeriodicEvaluation:
    """Everything the training loop needs: when to evaluate, the CSV row, the logger points.

    Args:
        cfg: the train config's ``eval`` node (:class:`PeriodicEvalConfig` keys; None: off).
        env_cfg: the training env config.
        run_dir: the run folder; rows go to ``eval_periodic.csv`` there.
        logger: a TorchRL logger (``log_scalar``) or None.
        device: where the evaluation episodes run (the batched engine and the network copy;
            None: the network's device).
    """

    def __init__(self, cfg: Mapping[str, Any] | DictConfig | None, env_cfg: Mapping[str, Any] | DictConfig,
                 run_dir: Path, logger: Any | None = None, device: torch.device | str | None = None) -> None:
        values = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg or {})
        self.cfg = PeriodicEvalConfig(**values)  # type: ignore[arg-type]
        if self.cfg.every < 0 or self.cfg.episodes < 1:
            raise ValueError(f"config 'eval': need every >= 0 and episodes >= 1, got {self.cfg}")
        self.env_cfg, self.logger, self.device = env_cfg, logger, device
        self.table = CsvTable(run_dir / PERIODIC_CSV, PERIODIC_FIELDS) if self.cfg.every else None
        self._frames = 0  # env steps at the last after_steps call

    def after_episode(self, qnet: nn.Module, episodes: int, env_steps: int) -> dict[str, float] | None:
        """``unit: episodes``: evaluate when ``episodes`` (done so far) is a multiple of
        ``every``; returns the row."""
        if self.table is None or self.cfg.unit != "episodes" or episodes % self.cfg.every:
            return None
        return self._evaluate(qnet, episodes, env_steps)

    def after_steps(self, qnet: nn.Module, episodes: int, env_steps: int) -> dict[str, float] | None:
        """``unit: env_steps``: evaluate when the steps since the last call crossed a multiple
        of ``every``; returns the row."""
        before, self._frames = self._frames, env_steps
        if self.table is None or self.cfg.unit != "env_steps" \
                or env_steps // self.cfg.every <= before // self.cfg.every:
            return None
        return self._evaluate(qnet, episodes, env_steps)

    def _evaluate(self, qnet: nn.Module, episodes: int, env_steps: int) -> dict[str, float]:
        assert self.table is not None
        metrics = periodic_eval(qnet, self.env_cfg, self.cfg.episodes, self.cfg.seed,
                                initial_lanes=self.cfg.initial_lanes, batch=self.cfg.batch,
                                device=self.device)
        row = {"episode": episodes, "env_steps": env_steps, **{k: round(v, 4) for k, v in metrics.items()}}
        self.table.append({k: row.get(k, "") for k in PERIODIC_FIELDS})
        if self.logger is not None:
            for key, value in metrics.items():
                self.logger.log_scalar(f"eval/{key}", float(value), step=env_steps)
        return metrics

    def rewind(self, episodes: int, env_steps: int) -> None:
        """After a resume from a checkpoint taken at ``episodes`` and ``env_steps``: keep the
        rows of evaluations made up to it (a row made after it passed one of the two)."""
        self._frames = env_steps
        if self.table is not None:
            rows = self.table.rows()
            self.table.truncate(next((i for i, r in enumerate(rows) if int(r["episode"]) > episodes
                                      or int(r["env_steps"]) > env_steps), len(rows)))
