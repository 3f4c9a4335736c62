"""``python -m memrl.evaluate [policy=checkpoint|scripted|random|human] [key=value ...]``.

Evaluates policies under the Table III protocol (``conf/protocol/paper.yaml``): the same
scenes for every policy, survival and goal scores for random and non-goal starts. A trained
run's results go into ``<run>/eval/`` (next to its ``config.yaml``, where the report finds
them), or ``<run>/eval_<type>/`` in other test traffic (``opponent=mixed``: ``eval_mixed/``, as
a study names it); other policies' into this command's Hydra run folder. A run's evaluation
made under another protocol is never replaced unless ``overwrite=true``.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import TYPE_CHECKING

import hydra
from omegaconf import DictConfig, OmegaConf

from memrl.cli import run_hydra, run_task
from memrl.configs import register_configs
from memrl.errors import instantiate_checked
from memrl.schemas import check_evaluate

if TYPE_CHECKING:  # the evaluation stack (torch) loads on the first run, not for --help
    from memrl.evaluation.policies import PolicySource
    from memrl.evaluation.protocol import ProtocolConfig
    from memrl.evaluation.results import EvalResult

log = logging.getLogger(__name__)


def workers_of(cfg: DictConfig) -> int:
    """The ``workers`` key: 0 means one process per CPU."""
    workers = int(cfg.workers)
    if workers < 0:
        raise ValueError(f"evaluate 'workers': need >= 0, got {workers}")
    return workers or os.cpu_count() or 1


def evaluate(cfg: DictConfig, out_dir: Path | None = None) -> list[EvalResult]:
    """Evaluate every candidate of ``cfg.policy`` and write their evaluation folders.

    Args:
        cfg: the composed ``evaluate`` config.
        out_dir: folder for policies that are not training runs (default: Hydra's
            ``paths.output_dir``).
    """
    from memrl.evaluation.policies import CheckpointSource
    from memrl.evaluation.protocol import check_protocol, eval_subdir
    from memrl.evaluation.session import evaluate_candidate, score_line

    check_evaluate(cfg)
    protocol = check_protocol(cfg.protocol)
    source: PolicySource = instantiate_checked(cfg.policy)  # type: ignore[assignment]
    policy_cfg = OmegaConf.to_container(cfg.policy, resolve=True)
    if isinstance(source, CheckpointSource) and source.subdir is None:
        source.subdir = eval_subdir(protocol.opponent)  # mixed cars: eval_mixed
        policy_cfg["subdir"] = source.subdir  # type: ignore[index,call-overload]
    candidates = source.candidates()
    resume = resumed(cfg, candidates) if cfg.get("resume") is not None else None
    if resume is not None:
        protocol = check_protocol(resume.protocol)  # the stopped evaluation's scenes
    elif not cfg.overwrite:
        for cand in candidates:
            refuse_other_protocol(cand.out_dir, protocol)
    results = []
    for cand in candidates:
        cand.meta["policy_config"] = policy_cfg
        result = evaluate_candidate(
            cand, protocol, env_cfg=cfg.env,
            out_dir=None if resume is not None else Path(out_dir or cfg.paths.output_dir),
            workers=workers_of(cfg), batch=int(cfg.batch), progress=bool(cfg.progress),
            resume=resume)
        print(score_line(result), f"-> {result.path}")
        results.append(result)
    return results


def refuse_other_protocol(folder: Path | None, protocol: ProtocolConfig,
                          remedy: str = "give policy.subdir=<another folder>, or overwrite=true "
                          "to replace it") -> None:
    """Raise when ``folder`` holds an evaluation made under another protocol (e.g. a run's
    ``eval/`` on constant-speed cars when this one is in mixed traffic): evaluating would
    replace it; ``remedy`` ends the message. An unreadable ``eval.json`` is replaced."""
    from dataclasses import asdict

    from memrl.errors import UserError
    from memrl.evaluation.protocol import protocol_id
    from memrl.evaluation.results import EVAL_JSON, read_result

    if folder is None or not (folder / EVAL_JSON).is_file():
        return
    try:
        old = read_result(folder)
    except (ValueError, KeyError, TypeError):
        return
    if old.protocol_id == protocol_id(protocol):
        return
    new = asdict(protocol)
    keys = sorted(k for k in set(old.protocol) | set(new)
                  if k != "initial_lanes" and old.protocol.get(k) != new.get(k))
    raise UserError(f"{folder} holds an evaluation under another protocol (differs in: "
                    f"{', '.join(keys) or 'its id'}); evaluating would replace it: {remedy}")


def resumed(cfg: DictConfig, candidates: list) -> EvalResult:
    """The stopped evaluation in ``cfg.resume``, checked to be this policy's (one candidate,
    the same name and unit, e.g. the same person)."""
    from memrl.errors import UserError
    from memrl.evaluation.results import EVAL_JSON, read_result
    from memrl.evaluation.session import is_complete

    folder = Path(str(cfg.resume))
    if not (folder / EVAL_JSON).is_file():
        raise UserError(f"resume: no {EVAL_JSON} in {folder} (give the folder a stopped evaluation printed)")
    try:
        old = read_result(folder)
    except (ValueError, KeyError, TypeError) as err:
        raise UserError(f"resume: {folder / EVAL_JSON}: unreadable ({err})") from None
    if len(candidates) != 1:
        raise UserError(f"resume: {folder} is one evaluation; this policy gives {len(candidates)}")
    cand = candidates[0]
    unit = str(cand.meta.get("unit", cand.name))
    if (old.name, old.unit) != (cand.name, unit):
        raise UserError(f"resume: {folder} is the evaluation of {old.name} [{old.unit}], not "
                        f"{cand.name} [{unit}]; give the same policy (and policy.person)")
    if is_complete(old):
        raise UserError(f"resume: {folder} is complete ({len(old.records())} episodes); nothing to do")
    return old


@hydra.main(version_base="1.3", config_path="conf", config_name="evaluate")
def main(cfg: DictConfig) -> None:
    run_task(evaluate, cfg)


if __name__ == "__main__":
    register_configs()
    run_hydra(main)
