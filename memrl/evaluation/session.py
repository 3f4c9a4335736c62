"""Evaluate one candidate policy under the protocol and write its evaluation folder."""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from memrl.evaluation.policies import Candidate
from memrl.evaluation.protocol import ProtocolConfig, protocol_env, scenario_seeds
from memrl.evaluation.results import EvalResult, write_result
from memrl.evaluation.runner import Job, run_jobs

log = logging.getLogger(__name__)


def evaluate_candidate(cand: Candidate, protocol: ProtocolConfig, *,
                       env_cfg: Mapping[str, Any] | DictConfig | None = None,
                       out_dir: Path | None = None, workers: int = 1, batch: int = 8,
                       progress: bool = False) -> EvalResult:
    """Run the protocol's episodes for ``cand`` and write ``eval.json`` + ``episodes.csv``.

    Args:
        cand: the policy, its env config and its results folder.
        protocol: the scenes and episode rules.
        env_cfg: base env config when the candidate has none (untrained policies).
        out_dir: results folder when the candidate names none.
        workers: processes (1: this one); a human always drives in this process.
        batch: episodes stepped in lockstep per process.
        progress: progress bar.
    """
    where = cand.out_dir or out_dir
    if where is None:
        raise ValueError(f"evaluate {cand.name}: no output folder")
    seeds = scenario_seeds(protocol.seed, protocol.episodes)
    base = cand.env if cand.env is not None else env_cfg
    jobs = [Job(protocol_env(base, protocol, lane), lane, list(enumerate(seeds)))
            for lane in protocol.initial_lanes]
    start = time.perf_counter()
    try:
        res = run_jobs(cand.actor, jobs, workers=workers, batch=batch, progress=progress,
                       desc=f"evaluate {cand.name}")
    finally:
        cand.actor.close()
    wall = time.perf_counter() - start
    if not res.records:
        raise RuntimeError(f"evaluate {cand.name}: no episode finished")
    result = write_result(Path(where), cand.name, res.records, protocol, seeds, cand.meta,
                          stopped_early=res.stopped_early, wall_s=wall, env=jobs[0].env,
                          extra={"workers": workers, "batch": batch,
                                 "steps": sum(r.steps for r in res.records)})
    steps = sum(r.steps for r in res.records)
    log.info("%s (%s): %d episodes, %d steps in %.1f s (%.0f steps/s) -> %s", cand.name,
             result.unit, len(res.records), steps, wall, steps / max(wall, 1e-9), where)
    return result


def score_line(result: EvalResult) -> str:
    """One line per result: survival / goal per initial-lane setting."""
    parts = [f"{lane}: survival {s.survival_score:.0f} goal {s.goal_score:.0f} (n={s.episodes})"
             for lane, s in result.scores.items()]
    return f"{result.name} [{result.unit}] " + "; ".join(parts)
