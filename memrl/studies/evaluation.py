"""The study's evaluations: every finished run, mode B's stage-1 weights, the baselines.

All on the study's protocol through :func:`memrl.evaluation.session.evaluate_candidate`. An
evaluation is reused when its ``eval.json`` was made under the same protocol after the
weights it scores were written; otherwise it is (re)made. Test traffic other than the paper's
constant-speed cars (``protocol.opponent``, e.g. mixed) has folders of its own beside the
constant ones (:func:`traffic_tag`), so one study is reported against both.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from memrl.evaluation.protocol import ProtocolConfig, eval_subdir, protocol_id, traffic_tag
from memrl.evaluation.results import EVAL_JSON, EvalResult, read_result

log = logging.getLogger(__name__)

STAGE1_SUFFIX = " stage 1"
"""Row label of a mode B row's stage-1 weights: ``B stage 1``."""


@dataclass
class EvalSettings:
    """How evaluations run."""

    protocol: ProtocolConfig
    workers: int = 1
    batch: int = 8
    progress: bool = False

    @property
    def tag(self) -> str:
        """:func:`traffic_tag` of the protocol's ``opponent``."""
        return traffic_tag(self.protocol.opponent)


@dataclass
class Evaluations:
    """The study's evaluations, and which of them were made by this call."""

    runs: list[EvalResult] = field(default_factory=list)
    stage1: list[EvalResult] = field(default_factory=list)
    baselines: list[EvalResult] = field(default_factory=list)
    made: list[str] = field(default_factory=list)
    """Evaluation folders written now."""
    reused: list[str] = field(default_factory=list)


def reusable(folder: Path, protocol: ProtocolConfig, weights: Path | None = None) -> EvalResult | None:
    """The evaluation in ``folder`` when it used ``protocol`` and is newer than ``weights``."""
    file = folder / EVAL_JSON
    if not file.is_file():
        return None
    result = read_result(file)
    if result.protocol_id != protocol_id(protocol):
        return None
    if weights is not None and weights.stat().st_mtime_ns > file.stat().st_mtime_ns:
        return None
    return result


def _evaluate(cand: Any, settings: EvalSettings, out: Evaluations, weights: Path | None,
              env: Mapping[str, Any] | None = None) -> EvalResult:
    from memrl.evaluation.session import evaluate_candidate

    assert cand.out_dir is not None
    found = reusable(cand.out_dir, settings.protocol, weights)
    if found is not None:
        cand.actor.close()
        out.reused.append(str(cand.out_dir))
        return found
    log.info("evaluating %s (%s) -> %s", cand.name, cand.meta.get("unit"), cand.out_dir)
    result = evaluate_candidate(cand, settings.protocol, env_cfg=env, workers=settings.workers,
                                batch=settings.batch, progress=settings.progress)
    out.made.append(str(cand.out_dir))
    return read_result(result.path)  # as a later call reads it (eval.json rounds the wall time)


def eval_folder(run: Path, settings: EvalSettings) -> Path:
    """Where a run's evaluation under the study's protocol goes: ``<run>/eval/``, or
    ``<run>/eval_<traffic>/`` for other test traffic (a later protocol of the same traffic
    replaces it)."""
    return run / eval_subdir(settings.protocol.opponent)


def evaluate_run(run: Path, settings: EvalSettings, out: Evaluations) -> None:
    """The final weights of a finished run (into :func:`eval_folder`)."""
    from memrl.evaluation.policies import CheckpointSource

    subdir = eval_folder(run, settings).name
    [cand] = CheckpointSource(str(run), subdir=subdir).candidates()
    cand.meta["policy_config"] = {"_target_": "memrl.evaluation.policies.CheckpointSource",
                                  "run": str(run), "name": None, "subdir": subdir}
    out.runs.append(_evaluate(cand, settings, out, run / "checkpoints" / "final.pt"))


def evaluate_runs(runs: list[Path], settings: EvalSettings, out: Evaluations) -> None:
    """:func:`evaluate_run` for each of ``runs`` (into ``out.runs`` in their order); the ones to
    (re)make that can share it on one batched engine per lane
    (:func:`memrl.evaluation.session.evaluate_candidates`: the same env config, e.g. seeds of one
    configuration), together."""
    from memrl.evaluation.policies import CheckpointSource
    from memrl.evaluation.session import evaluate_candidates

    found: dict[Path, EvalResult] = {}
    todo = []
    for run in runs:
        subdir = eval_folder(run, settings).name
        [cand] = CheckpointSource(str(run), subdir=subdir).candidates()
        cand.meta["policy_config"] = {"_target_": "memrl.evaluation.policies.CheckpointSource",
                                      "run": str(run), "name": None, "subdir": subdir}
        assert cand.out_dir is not None
        reuse = reusable(cand.out_dir, settings.protocol, run / "checkpoints" / "final.pt")
        if reuse is not None:
            cand.actor.close()
            out.reused.append(str(cand.out_dir))
            found[run] = reuse
        else:
            todo.append((run, cand))
    if todo:
        log.info("evaluating %s -> %s", ", ".join(c.name for _, c in todo),
                 ", ".join(str(c.out_dir) for _, c in todo))
        made = evaluate_candidates([c for _, c in todo], settings.protocol, workers=settings.workers,
                                   batch=settings.batch, progress=settings.progress)
        for (run, cand), result in zip(todo, made, strict=True):
            out.made.append(str(cand.out_dir))
            found[run] = read_result(result.path)  # as a later call reads it (eval.json rounds the wall time)
    out.runs += [found[run] for run in runs]


def evaluate_stage1(run: Path, folder: Path, settings: EvalSettings, out: Evaluations) -> None:
    """Mode B's stage-1 weights (``checkpoints/stage1.pt``) into ``folder``; skipped when the
    run has none."""
    from memrl.checkpoint import load_stage1_qnet
    from memrl.evaluation.policies import Candidate, CheckpointSource, GreedyActor, run_config, run_gamma

    weights = run / "checkpoints" / "stage1.pt"
    if not weights.is_file():
        log.info("%s has no stage-1 weights; skipped", run)
        return
    [final] = CheckpointSource(str(run)).candidates()
    final.actor.close()
    cfg = run_config(run)
    cand = Candidate(final.name + STAGE1_SUFFIX, GreedyActor(load_stage1_qnet(weights), gamma=run_gamma(cfg)),
                     env=cfg.get("env"), out_dir=folder,
                     meta={"kind": "stage1", "run": str(run), "mode": final.meta["mode"],
                           "train_seed": cfg.get("seed"), "unit": f"seed {cfg.get('seed')}"})
    out.stage1.append(_evaluate(cand, settings, out, weights))


def evaluate_stage1s(pairs: list[tuple[Path, Path]], settings: EvalSettings, out: Evaluations) -> None:
    """:func:`evaluate_stage1` for each (run, folder)."""
    for run, folder in pairs:
        evaluate_stage1(run, folder, settings, out)


def evaluate_baseline(name: str, env: DictConfig, folder: Path, settings: EvalSettings,
                      out: Evaluations) -> None:
    """An untrained policy (``conf/policy/<name>.yaml``) in the runs' env, into ``folder``."""
    from hydra.utils import instantiate

    from memrl.studies.grid import compose_config

    policy = compose_config("evaluate", [f"policy={name}"]).policy
    [cand] = instantiate(policy).candidates()
    cand.meta["policy_config"] = OmegaConf.to_container(policy, resolve=True)
    cand.out_dir = folder
    out.baselines.append(_evaluate(cand, settings, out, None,
                                   env=OmegaConf.to_container(env, resolve=True)))  # type: ignore[arg-type]
