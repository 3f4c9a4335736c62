"""Evaluate one candidate policy under the protocol and write its evaluation folder."""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from memrl.evaluation.crash_sight import summarize
from memrl.evaluation.jobs import JobResult
from memrl.evaluation.policies import Candidate
from memrl.evaluation.protocol import INITIAL_LANES, ProtocolConfig, protocol_env, scenario_seeds
from memrl.evaluation.results import EvalResult, write_result
from memrl.evaluation.runner import Job, run_jobs
from memrl.evaluation.sight_tables import evaluation_markdown
from memrl.stop import Interrupted, SignalGuard, Stopped, how_stopped, interrupted_by, output_overrides

log = logging.getLogger(__name__)

EVAL_MD = "eval.md"
"""An evaluation folder's markdown: its scores and the section "Does the learner see its crash
coming" (:func:`~memrl.evaluation.sight_tables.evaluation_markdown`)."""


def evaluate_candidate(cand: Candidate, protocol: ProtocolConfig, *,
                       env_cfg: Mapping[str, Any] | DictConfig | None = None,
                       out_dir: Path | None = None, workers: int = 1, batch: int = 8,
                       progress: bool = False, resume: EvalResult | None = None) -> EvalResult:
    """Run the protocol's episodes for ``cand`` and write ``eval.json`` + ``episodes.csv``, and
    ``eval.md`` (the scores and the crash-sight section). An actor that gives its Q-values and
    knows their discount (a trained run's :class:`~memrl.evaluation.policies.GreedyActor`) has
    its episodes recorded as they are driven: ``eval.json``'s ``crash_sight``
    (:func:`memrl.evaluation.crash_sight.summarize`; of this call's episodes on a resume).

    Args:
        cand: the policy, its env config and its results folder.
        protocol: the scenes and episode rules.
        env_cfg: base env config when the candidate has none (untrained policies).
        out_dir: results folder when the candidate names none.
        workers: processes (1: this one); a human always drives in this process.
        batch: episodes stepped in lockstep per process.
        progress: progress bar.
        resume: a stopped evaluation of the same unit under the same protocol: only its
            missing episodes are driven (same scene seeds), and the folder gets all of them.

    Raises:
        Stopped: a person ended it (Esc) or a signal came before every episode finished:
            what finished is written (``stopped_early``) and the line names the command that
            goes on with it; before any finished episode, nothing is written.
        Interrupted: a signal before any episode finished (nothing written; the command's
            line says so and names the command again).
    """
    plan = _plan(cand, protocol, env_cfg, out_dir, resume)
    start = time.perf_counter()
    try:
        with SignalGuard():
            res = run_jobs(cand.actor, [j for j in plan.jobs if j.episodes], workers=workers, batch=batch,
                           progress=progress, desc=f"evaluate {cand.name}", record=plan.record)
    except (KeyboardInterrupt, Interrupted) as err:  # between jobs, or in worker processes
        res = JobResult(stopped_early=True, interrupted=interrupted_by(err))
    finally:
        cand.actor.close()
    return _write(cand, protocol, plan, res, time.perf_counter() - start, resume,
                  {"workers": workers, "batch": batch})


@dataclass
class _Plan:
    """What one candidate's evaluation drives: its folder, scenes, jobs and whether it records."""

    where: Path
    seeds: list[int]
    jobs: list[Job]
    total: int
    record: bool
    gamma: float | None


def _plan(cand: Candidate, protocol: ProtocolConfig, env_cfg: Mapping[str, Any] | DictConfig | None,
          out_dir: Path | None, resume: EvalResult | None) -> _Plan:
    where = resume.path if resume is not None else (cand.out_dir or out_dir)
    if where is None:
        raise ValueError(f"evaluate {cand.name}: no output folder")
    seeds = scenario_seeds(protocol.seed, protocol.episodes)
    base = cand.env if cand.env is not None else env_cfg
    done = {(r.initial_lane, r.episode) for r in resume.records()} if resume is not None else set()
    jobs = [Job(protocol_env(base, protocol, lane), lane,
                [(i, s) for i, s in enumerate(seeds) if (lane, i) not in done])
            for lane in protocol.initial_lanes]
    total = len(seeds) * len(protocol.initial_lanes)
    if hasattr(cand.actor, "plan"):
        cand.actor.plan(total, done=len(done))
    gamma = getattr(cand.actor, "gamma", None)
    return _Plan(Path(where), list(seeds), jobs, total, cand.actor.gives_values and gamma is not None, gamma)


def _write(cand: Candidate, protocol: ProtocolConfig, plan: _Plan, res: JobResult, seconds: float,
           resume: EvalResult | None, extra: dict[str, Any]) -> EvalResult:
    """Write the evaluation folder of ``res`` (the episodes driven now, after ``resume``'s)."""
    where, total, gamma = plan.where, plan.total, plan.gamma
    stop = res.interrupted
    wall = seconds + (resume.wall_s if resume is not None else 0.0)
    records = sorted([*(resume.records() if resume is not None else []), *res.records],
                     key=lambda r: (protocol.initial_lanes.index(r.initial_lane), r.episode))
    if not res.records and stop is not None:  # a signal: the command's one line, with the command again
        raise stop
    if not res.records and res.stopped_early:  # Esc in a person's window
        raise Stopped("stopped before any episode finished; nothing saved")
    if not records:
        raise RuntimeError(f"evaluate {cand.name}: no episode finished")
    stopped = res.stopped_early or len(records) < total
    gamma_risk = getattr(getattr(cand.actor, "net", None), "gamma_risk", None)  # a crash-risk head's
    sight = summarize(res.traces, float(gamma), protocol.duration, gamma_risk) \
        if gamma is not None and plan.record and res.traces else None
    result = write_result(where, cand.name, records, protocol, plan.seeds, cand.meta,
                          stopped_early=stopped, wall_s=wall, env=plan.jobs[0].env,
                          extra={**extra, "episodes_planned": total,
                                 "steps": sum(r.steps for r in records)}, crash_sight=sight)
    (where / EVAL_MD).write_text(evaluation_markdown(result))
    steps = sum(r.steps for r in res.records)
    log.info("%s (%s): %d episodes, %d steps in %.1f s (%.0f steps/s) -> %s", cand.name,
             result.unit, len(res.records), steps, wall, steps / max(wall, 1e-9), where)
    if stopped:
        print(score_line(result), f"-> {result.path}")
        raise Stopped.by(f"{how_stopped(stop)} after {len(records)} of {total} episodes, saved in {where}; "
                         f"go on with: {resume_command(cand, where)}", stop)
    return result


def together(cands: Sequence[Candidate], plans: Sequence[_Plan]) -> bool:
    """Whether the candidates can share one engine: at least two tensor-policy actors, the same
    jobs (env configs, lanes, scenes), which the engine runs."""
    from memrl.evaluation.engine_runner import engine_can_run

    first = plans[0].jobs
    same = all([(j.env, j.initial_lane, j.episodes) for j in p.jobs] ==
               [(j.env, j.initial_lane, j.episodes) for j in first] for p in plans)
    return len(cands) > 1 and same and all(c.actor.tensor_policy for c in cands) and \
        all(engine_can_run(j) for j in first)


def evaluate_candidates(cands: Sequence[Candidate], protocol: ProtocolConfig, *,
                        env_cfg: Mapping[str, Any] | DictConfig | None = None, workers: int = 1,
                        batch: int = 8, progress: bool = False, share: bool = False) -> list[EvalResult]:
    """:func:`evaluate_candidate` for each of ``cands``; with ``share``, where they can share it
    (:func:`together`: e.g. K checkpoints of one configuration), all on one batched engine per
    lane (:func:`~memrl.evaluation.engine_runner.run_actors_on_engine`), each folder what its own
    evaluation writes (``eval.json``'s ``extra.together`` counts the candidates driven with it,
    its ``wall_s`` is theirs together). A signal before they finish writes nothing.

    ``share`` is off by default: on the CPU engine (where every evaluation runs today) five
    networks on one engine took 1.05-1.18x the time of one after the other
    (``python -m memrl.bench eval eval.checkpoints=5``, docs/performance.md); the engine's own
    step is a small part of an evaluation there."""
    from memrl.evaluation.engine_runner import run_actors_on_engine
    from memrl.progress import progress_bar

    plans = [_plan(c, protocol, env_cfg, None, None) for c in cands]
    if not (share and together(cands, plans)):
        return [evaluate_candidate(c, protocol, env_cfg=env_cfg, workers=workers, batch=batch,
                                   progress=progress) for c in cands]
    jobs = [j for j in plans[0].jobs if j.episodes]
    bar = progress_bar(progress, total=len(cands) * sum(len(j.episodes) for j in jobs),
                       desc=f"evaluate {len(cands)} together", unit="ep")
    start = time.perf_counter()
    try:
        with SignalGuard():
            results = run_actors_on_engine([c.actor for c in cands], jobs, threads=max(1, workers),
                                           on_done=bar.update, record=any(p.record for p in plans))
    except (KeyboardInterrupt, Interrupted) as err:
        raise interrupted_by(err) from None
    finally:
        bar.close()
        for c in cands:
            c.actor.close()
    seconds = time.perf_counter() - start
    order = {lane: i for i, lane in enumerate(INITIAL_LANES)}
    for r in results:  # as run_jobs orders them: the crash-sight sums run in this order
        r.records.sort(key=lambda x: (order[x.initial_lane], x.episode))
        r.traces.sort(key=lambda x: (order[x.initial_lane], x.episode))
    return [_write(c, protocol, p, r, seconds, None, {"workers": workers, "together": len(cands)})
            for c, p, r in zip(cands, plans, results, strict=True)]


def resume_command(cand: Candidate, where: Path | str) -> str:
    """The command that goes on with a stopped evaluation in ``where``."""
    import shlex

    kind, person = cand.meta.get("kind"), cand.meta.get("person")
    policy = {"human": "policy=human" + (f" policy.person={person}" if person else ""),
              "driver": f"policy={cand.name}", "checkpoint": f"policy.run={cand.meta.get('run')}",
              "python": f"policy=python policy.target={cand.meta.get('target')}",
              "sb3": f"policy=sb3 policy.path={cand.meta.get('path')}"}
    if kind in ("python", "sb3") and (given := policy_overrides()):  # its kwargs and env as given
        policy[str(kind)] = " ".join(map(shlex.quote, given))
    command = f"python -m memrl.evaluate {policy.get(str(kind), '')} resume={where}".replace("  ", " ")
    return " ".join([command, *map(shlex.quote, output_overrides())])


def policy_overrides() -> list[str]:
    """This Hydra run's overrides of ``policy`` and its keys (none outside a Hydra run)."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return []
    return [str(o) for o in HydraConfig.get().overrides.task
            if str(o).split("=", 1)[0].lstrip("+").split(".")[0] == "policy"]



def is_complete(result: EvalResult) -> bool:
    """Every episode of the protocol is in the evaluation (a stopped one is partial)."""
    planned = int(result.protocol.get("episodes", 0)) * len(result.protocol.get("initial_lanes", []))
    return not result.stopped_early and sum(s.episodes for s in result.scores.values()) >= planned


def score_line(result: EvalResult) -> str:
    """One line per result: survival / goal per initial-lane setting."""
    parts = [f"{lane}: survival {s.survival_score:.0f} goal {s.goal_score:.0f} (n={s.episodes})"
             for lane, s in result.scores.items()]
    return f"{result.name} [{result.unit}] " + "; ".join(parts)
