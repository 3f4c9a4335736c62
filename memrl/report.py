"""``python -m memrl.report runs=[<run, multirun or evaluation folders>]``: Table III, Fig. 5, Fig. 7.

Finds every evaluation (``eval.json``) and training run (``episodes.csv``) below the given
folders; with ``evaluate_missing`` it first evaluates trained runs that have no evaluation
under the configured protocol. Writes into its Hydra run folder: ``table3.md``,
``table3.csv`` (mean and IQM with stratified-bootstrap intervals, per-seed values; rows are
whole configurations), ``differences.csv`` (differences and P(a > b) with intervals),
``fig5.png``, ``fig7_<row>.png``, ``rollouts_<row>.mp4`` and ``report.json``, and prints the
markdown table.
"""

from __future__ import annotations

import json
import logging
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import hydra
from omegaconf import DictConfig, OmegaConf

from memrl.cli import run_hydra, run_task
from memrl.configs import register_configs
from memrl.errors import config_error
from memrl.evaluate import refuse_other_protocol, workers_of
from memrl.schemas import check_report

if TYPE_CHECKING:  # the evaluation stack (torch) loads on the first run, not for --help
    from memrl.evaluation.results import EvalResult
    from memrl.evaluation.rows import RowGroup
    from memrl.evaluation.stats import StatsConfig

log = logging.getLogger(__name__)


@dataclass
class ReportFiles:
    """What the report wrote."""

    table_md: Path
    table_csv: Path
    differences_csv: Path
    report_json: Path
    fig5: Path | None = None
    strips: list[Path] = field(default_factory=list)
    videos: list[Path] = field(default_factory=list)
    markdown: str = ""


def evaluate_missing(cfg: DictConfig) -> list[EvalResult]:
    """Evaluate the trained runs under ``cfg.runs`` that have no evaluation under
    ``cfg.protocol``, in the folder ``memrl.evaluate`` and the study use (``eval/``; ``eval_mixed/``
    for mixed test traffic: :func:`~memrl.evaluation.protocol.eval_subdir`). A folder holding an
    evaluation under another protocol is replaced only with ``overwrite=true``; otherwise the
    report refuses, in one line, before evaluating anything."""
    from memrl.evaluation.policies import CheckpointSource
    from memrl.evaluation.protocol import check_protocol, eval_subdir, protocol_id
    from memrl.evaluation.results import EVAL_JSON, read_result
    from memrl.evaluation.session import evaluate_candidate

    protocol = check_protocol(cfg.protocol)
    wanted = protocol_id(protocol)
    todo = []
    for item in cfg.runs:
        try:
            source = CheckpointSource(str(item), subdir=eval_subdir(protocol.opponent))
        except FileNotFoundError:
            continue  # no training run there (e.g. an evaluation folder)
        for cand in source.candidates():
            assert cand.out_dir is not None
            existing = cand.out_dir / EVAL_JSON
            if existing.is_file() and read_result(existing).protocol_id == wanted:
                continue
            if not cfg.overwrite:
                refuse_other_protocol(cand.out_dir, protocol, remedy="overwrite=true to replace it, "
                                      "or evaluate_missing=false to report the evaluations there are")
            todo.append(cand)
    if todo:  # before evaluating anything: the report would find two protocols afterwards
        from memrl.evaluation import stats
        from memrl.evaluation.results import find_results
        from memrl.evaluation.session import is_complete

        planned = {Path(str(c.out_dir)).resolve() for c in todo}
        kept = [r for r in find_results([str(x) for x in cfg.runs])
                if is_complete(r) and Path(r.path).resolve() not in planned]
        stats.check_protocols([*kept, *(_planned_result(c, wanted) for c in todo)])
    done = []
    for cand in todo:
        log.info("evaluating %s (%s)", cand.meta["run"], cand.name)
        done.append(evaluate_candidate(cand, protocol, workers=workers_of(cfg),
                                       batch=int(cfg.batch), progress=bool(cfg.progress)))
    return done


def _planned_result(cand: Any, protocol_id: str) -> Any:
    """What :func:`stats.check_protocols` reads of an evaluation still to be made."""
    from types import SimpleNamespace

    return SimpleNamespace(protocol_id=protocol_id, path=cand.out_dir)


def _rows_named(groups: list[RowGroup], name: str) -> list[RowGroup]:
    """The row labelled ``name``, else every row of that name (one per configuration)."""
    exact = [g for g in groups if g.label == name]
    return exact or [g for g in groups if g.base == name]


def _rollouts(cfg: DictConfig, results: list[EvalResult], out: Path, files: ReportFiles) -> None:
    from memrl.evaluation import stats

    r = cfg.rollouts
    groups = stats.rows_of(results, stats_config(cfg))
    for name in r.rows:
        named = _rows_named(groups, str(name))
        if not named:
            log.info("fig. 7: no evaluation of row %s; skipped", name)
        for g in named:
            _rollout_row(cfg, g, out, files)


def _rollout_row(cfg: DictConfig, g: RowGroup, out: Path, files: ReportFiles) -> None:
    """Fig. 7 strip and video of one row's first unit (or ``rollouts.unit``), and strips of its
    crashes by kind (``rollouts.crashes`` per kind, the last ``rollouts.crash_frames`` steps)."""
    from memrl.evaluation import rollouts

    r = cfg.rollouts
    label, units = g.label, g.results
    if r.unit is not None:
        units = [u for u in units if u.unit == str(r.unit)]
    if not units:
        log.info("fig. 7: no evaluation of row %s%s; skipped", label,
                 f" unit {r.unit}" if r.unit is not None else "")
        return
    result = units[0]
    actor = rollouts.actor_for(result)
    if actor is None:
        log.info("fig. 7: %s cannot be replayed (a person drove); skipped", label)
        return
    lane = str(r.initial_lane)
    episodes = rollouts.pick_episodes(result, lane, int(r.count), str(r.pick))
    title = f"Fig. 7: {label}, {result.unit}, {lane.replace('_', '-')} starts"
    note = None
    if r.pick == "success" and not rollouts.successes(result, lane):
        total = sum(x.initial_lane == lane for x in result.records())
        note = (f"no episode of {label} ({result.unit}) changed into the target lane without a collision "
                f"(0 of {total}); these are its first episodes")
    caps = [rollouts.capture(actor, result, str(r.initial_lane), e) for e in episodes]
    for c in caps:  # the replay must be the evaluated episode
        rec = next(x for x in result.records() if x.initial_lane == r.initial_lane
                   and x.episode == c.record.episode)
        if (rec.steps, rec.collided, rec.reached_target) != \
                (c.record.steps, c.record.collided, c.record.reached_target):
            log.warning("fig. 7: replay of %s episode %d differs from its evaluation", label, rec.episode)
    name = re.sub(r"[^A-Za-z0-9.=-]+", "_", label).strip("_")  # Default_total_frames=1
    steps = None if r.steps is None else [int(x) for x in r.steps]
    picture = rollouts.strip(caps, steps, float(r.scale), title=title, note=note)
    files.strips.append(rollouts.write_png(picture, out / f"fig7_{name}.png"))
    if r.video:
        files.videos.append(rollouts.write_video(caps, out / f"rollouts_{name}.mp4", float(r.fps)))
    if int(r.get("crashes", 0)):
        from memrl.evaluation.crash_strips import crash_strips

        for kind, img in crash_strips(actor, result, label, int(r.crashes), int(r.crash_frames),
                                      float(r.scale)).items():
            files.strips.append(rollouts.write_png(img, out / f"crashes_{name}_{kind}.png"))


def _plain(cfg: DictConfig, out: Path) -> dict:
    """The resolved config (resolvable outside a Hydra run too)."""
    saved = cfg.copy()
    saved.paths.output_dir = str(out)
    return OmegaConf.to_container(saved, resolve=True)  # type: ignore[return-value]


def stats_config(cfg: DictConfig) -> StatsConfig:
    """The statistics settings of the report config."""
    from memrl.evaluation.stats import StatsConfig

    return StatsConfig(float(cfg.confidence), int(cfg.n_resamples), int(cfg.bootstrap_seed),
                       tuple(str(k) for k in cfg.row_ignore))


def planned_episodes(result: EvalResult) -> int:
    return int(result.protocol.get("episodes", 0)) * len(result.protocol.get("initial_lanes", []))


def partial_note(partial: list[EvalResult]) -> str:
    """The evaluations left out of the table because their protocol is not complete."""
    if not partial:
        return ""
    lines = ["", "### Partial evaluations (not counted in the table)", "",
             "| method | unit | episodes | folder |", "|---|---|---|---|"]
    for r in partial:
        done = sum(s.episodes for s in r.scores.values())
        lines.append(f"| {r.name} | {r.unit} | {done} of {planned_episodes(r)} (partial) | {r.path} |")
    lines += ["", "Go on with one: python -m memrl.evaluate policy=human policy.person=<name> "
              "resume=<folder>."]
    return "\n".join(lines) + "\n"


def report(cfg: DictConfig, out_dir: Path | None = None) -> ReportFiles:
    """Build Table III (markdown + CSV), the pairwise differences, Fig. 5 and Fig. 7.

    Args:
        cfg: the composed ``report`` config.
        out_dir: where to write (default: Hydra's ``paths.output_dir``).
    """
    from memrl.evaluation import figures, stats, tables
    from memrl.evaluation.crashes import crash_section
    from memrl.evaluation.results import find_results
    from memrl.evaluation.session import is_complete
    from memrl.evaluation.sight_tables import sight_section

    check_report(cfg)
    out = Path(out_dir or cfg.paths.output_dir)
    if cfg.evaluate_missing:
        evaluate_missing(cfg)
    found = find_results([str(p) for p in cfg.runs])
    results = [r for r in found if is_complete(r)]
    partial = [r for r in found if not is_complete(r)]
    if not results:
        what = (f"only partial evaluations ({', '.join(str(r.path) for r in partial)}); finish them "
                "with python -m memrl.evaluate ... resume=<folder>" if partial else
                "no evaluation (eval.json)")
        raise config_error("runs", f"{what} under {', '.join(map(str, cfg.runs))}; "
                           "run python -m memrl.evaluate first or set evaluate_missing=true")
    pid = stats.check_protocols(results)  # before the report's folder is made
    out.mkdir(parents=True, exist_ok=True)
    scfg = stats_config(cfg)
    rows = stats.table(results, scfg)
    diffs = stats.differences(results, [list(p) for p in cfg.comparisons], scfg)
    md = tables.markdown(rows, diffs, scfg.confidence) + partial_note(partial)
    md += "\n" + "\n".join(crash_section([results], scfg))
    md += "\n" + "\n".join(sight_section([results], scfg))
    files = ReportFiles(out / "table3.md", out / "table3.csv", out / "differences.csv",
                        out / "report.json", markdown=md)
    files.table_md.write_text(md)
    tables.write_csv(rows, diffs, files.table_csv, files.differences_csv)
    print(md)
    if cfg.fig5:
        files.fig5 = figures.learning_curves(
            figures.find_training_runs([str(p) for p in (cfg.runs if cfg.get("train_runs") is None
                                                         else cfg.train_runs)]), out / "fig5.png",
            window=int(cfg.smooth), confidence=scfg.confidence, n_resamples=int(cfg.curve_resamples))
    if cfg.rollouts.rows:
        _rollouts(cfg, results, out, files)
    doc = {
        "protocol_id": pid, "protocol": results[0].protocol,
        "rows": [{"label": r.label, "base": r.base, "config": r.variant, "units": r.units,
                  "cells": {f"{lane}/{metric}": asdict(c) for (lane, metric), c in r.cells.items()}}
                 for r in rows],
        "differences": [{"a": d.a, "b": d.b, "column": "/".join(d.column), **asdict(d.cell),
                         "excludes_zero": d.cell.excludes_zero(), "p_improvement": d.p_improvement,
                         "p_low": d.p_low, "p_high": d.p_high} for d in diffs],
        "sources": [str(r.path) for r in results],
        "partial": [{"path": str(r.path), "name": r.name, "unit": r.unit,
                     "episodes": sum(s.episodes for s in r.scores.values()),
                     "planned": planned_episodes(r)} for r in partial],
        "files": {k: [str(p) for p in v] if isinstance(v, list) else (str(v) if v else None)
                  for k, v in asdict(files).items() if k != "markdown"},
        "config": _plain(cfg, out),
    }
    files.report_json.write_text(json.dumps(doc, indent=2))
    for path in [files.table_md, files.fig5, *files.strips, *files.videos]:
        if path is not None:
            print(f"wrote {path}")
    return files


@hydra.main(version_base="1.3", config_path="conf", config_name="report")
def main(cfg: DictConfig) -> None:
    run_task(report, cfg)


if __name__ == "__main__":
    register_configs()
    run_hydra(main)
