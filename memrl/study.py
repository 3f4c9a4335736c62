"""``python -m memrl.study [study.modes=[...]] [study.seeds=[...]] study.train_overrides=[...]``.

Table III from real training, in one folder (``study.dir``): every ([variant,] mode, opponent,
seed) run under ``runs/``, its evaluation on the protocol (``runs/<run>/eval/``, made as the run
finishes: ``study.evaluate``), mode B's stage-1
weights evaluated too (``stage1/``), the scripted and random baselines (``baselines/``), then
``report.md``, ``table3.csv`` and the figures. The same command again resumes: finished runs
are skipped, killed ones resume from their last checkpoint, finished evaluations are reused,
and a finished study is only reported again. Test traffic other than constant-speed cars
(``protocol.opponent``) keeps its own folders (``eval_<traffic>/``, ``*_<traffic>/``) and its
report in ``test_<traffic>/``: a second call reports the same runs against it. Pieces: :mod:`memrl.studies`.
"""

from __future__ import annotations

import json
import logging
import shlex
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import hydra
from omegaconf import DictConfig, OmegaConf

from memrl.cli import run_hydra, run_task
from memrl.configs import register_configs
from memrl.errors import config_error
from memrl.modes import MODES, by_label
from memrl.schemas import check_study
from memrl.studies.record import STUDY_JSON, read_record, record_lock, write_record

if TYPE_CHECKING:  # torch and the trainer load on the first run, not for --help
    from memrl.studies.grid import Cell, Outcome

log = logging.getLogger(__name__)


@dataclass
class StudyResult:
    """What a call of :func:`study` did and wrote."""

    dir: Path
    report: Path
    table_csv: Path
    skipped: list[str] = field(default_factory=list)
    """Runs finished before this call."""
    trained: list[str] = field(default_factory=list)
    resumed: list[str] = field(default_factory=list)
    extended: list[str] = field(default_factory=list)
    """Runs this call began as copies of an earlier study's (``study.extend_from``), then resumed."""
    failed: dict[str, str] = field(default_factory=dict)
    evaluated: list[str] = field(default_factory=list)
    """Evaluation folders written by this call."""
    reused: list[str] = field(default_factory=list)
    figures: list[Path] = field(default_factory=list)
    wall_s: float = 0.0
    command: str = ""


def command_line(cfg: DictConfig) -> str:
    """The command that made this call, quoted for a POSIX shell: Hydra's overrides, or the
    study keys of a typed call."""
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        args = [str(a) for a in HydraConfig.get().overrides.task]
    else:
        s = cfg.study
        args = [f"study.dir={s.dir}", f"study.modes=[{','.join(s.modes)}]",
                f"study.seeds=[{','.join(map(str, s.seeds))}]",
                f"study.opponents=[{','.join(s.opponents)}]", f"study.jobs={s.jobs}",
                f"study.seeds_per_process={s.seeds_per_process}",
                f"study.train_overrides={json.dumps(list(s.train_overrides))}"]
        if s.get("extend_from"):
            args.append(f"study.extend_from={s.extend_from}")
        if s.get("variants"):
            args.append("study.variants={" + ",".join(f"{k}:{json.dumps(v)}"
                                                      for k, v in variants_of(cfg).items()) + "}")
        protocol: dict[str, Any] = OmegaConf.to_container(cfg.protocol, resolve=True)  # type: ignore[assignment]
        args += [f"protocol.{k}={json.dumps(v).replace(' ', '')}" for k, v in protocol.items()]
    return " ".join(["python -m memrl.study", *(shlex.quote(a) for a in args)])


def variants_of(cfg: DictConfig) -> dict[str, list[str]]:
    """``study.variants`` as plain values."""
    return {str(k): [str(o) for o in v] for k, v in (cfg.study.get("variants") or {}).items()}


def check_record(folder: Path, cfg: DictConfig) -> None:
    """Refuse a study folder made with other train overrides or other variants (unless
    ``allow_changes``), then record this call's grid in ``study.json``.

    A call may leave recorded variants out (as it may leave out seeds); a new variant, or one
    with other overrides, is a change. The record keeps every variant ever run.
    """
    with record_lock(folder) as file:
        doc = read_record(file)
        write_record(file, checked_record(doc, folder, cfg))


def checked_record(doc: dict[str, Any], folder: Path, cfg: DictConfig) -> dict[str, Any]:
    """:func:`check_record`'s checks of this call against the record ``doc``; the new record
    (keys this function does not know, e.g. ``extended``, kept)."""
    s = cfg.study
    now = [str(o) for o in s.train_overrides]
    variants = variants_of(cfg)
    before = doc.get("train_overrides", now)
    if before != now and not s.allow_changes:
        raise config_error("study.train_overrides", f"the study {folder} was made with {before}, this "
                           f"call gives {now}; give the same, another study.dir, or study.allow_changes=true "
                           "(finished runs are then kept as they are)")
    known: dict[str, list[str]] = doc.get("variants", {}) if doc else dict(variants)  # no record: none known
    changed = {k: v for k, v in variants.items() if known.get(k) != v}
    if changed and not s.allow_changes:
        made = ", ".join(f"{k}: {v}" for k, v in known.items()) or "no variants"
        raise config_error("study.variants", f"the study {folder} was made with {made}; this call adds or "
                           f"changes {', '.join(f'{k}: {v}' for k, v in changed.items())}; give the same, "
                           "another study.dir, or study.allow_changes=true (finished runs are then kept "
                           "as they are)")
    history = doc.get("changes", [])
    stamp = time.strftime("%Y-%m-%d %H:%M:%S")
    if before != now:
        history.append({"from": before, "to": now, "at": stamp})
    if changed:
        history.append({"key": "study.variants", "from": {k: known[k] for k in changed if k in known},
                        "to": changed, "at": stamp})
    return {**doc, "train_overrides": now, "variants": {**known, **variants}, "modes": list(s.modes),
            "seeds": list(s.seeds), "opponents": list(s.opponents), "baselines": list(s.baselines),
            "protocol": OmegaConf.to_container(cfg.protocol, resolve=True), "changes": history}


def _quote(items: list[str]) -> str:
    """A Hydra list override of quoted strings (labels hold spaces and brackets)."""
    return "[" + ",".join("'" + i.replace("'", "\\'") + "'" for i in items) + "]"


def report_config(cfg: DictConfig, folders: list[Path], labels: list[str],
                  comparisons: list[list[str]], train_runs: list[Path]) -> DictConfig:
    """The report config of the study: its evaluation folders, the training runs of Fig. 5, its
    rows, the user's report overrides."""
    from memrl.studies.grid import compose_config

    overrides = [f"runs={_quote([str(f) for f in folders])}", "evaluate_missing=false",
                 f"train_runs={_quote([str(f) for f in train_runs])}",
                 f"progress={str(bool(cfg.study.progress)).lower()}",
                 f"comparisons=[{','.join(_quote(p) for p in comparisons)}]",
                 f"rollouts.rows={_quote(labels)}", "rollouts.video=false",
                 *[str(o) for o in cfg.study.report_overrides]]
    return compose_config("report", overrides)


def comparison_pairs(grid: list[Cell], labels: list[str]) -> list[list[str]]:
    """Each mode against the baseline (the mode no ``+mode`` selects: Default) within each
    (variant, traffic), the latest declared first: ``[B (cue), Default (cue)]``, then A's."""
    suffixes = dict.fromkeys(c.label[len(c.mode):] for c in grid)
    base = next(m.label for m in MODES.values() if not m.overrides)
    others = [m.label for m in reversed(MODES.values()) if m.overrides]  # R, B, A
    return [[f"{m}{sfx}", f"{base}{sfx}"] for m in others for sfx in suffixes
            if f"{base}{sfx}" in labels and f"{m}{sfx}" in labels]


def trained_only(cfg: DictConfig, folder: Path, outcome: Outcome, extended: list[str],
                 start: float) -> StudyResult:
    """``study.evaluate=none``: what the training did, no evaluation and no report."""
    result = StudyResult(folder, folder / "report.md", folder / "table3.csv", outcome.skipped,
                         outcome.trained, outcome.resumed, extended, outcome.failed,
                         command=command_line(cfg), wall_s=time.perf_counter() - start)
    log.info("study %s: %d runs skipped, %d trained, %d resumed, %d failed; not evaluated "
             "(study.evaluate=none): the same command with study.train=false evaluates and reports them",
             folder, len(result.skipped), len(result.trained), len(result.resumed), len(result.failed))
    return result


def seeds_per_process(cfg: DictConfig, grid: list[Cell]) -> int:
    """``study.seeds_per_process``, or 1 where the runs' config keeps them apart
    (:func:`memrl.train.group_refusal`), said once."""
    from memrl.train import group_refusal

    k = int(cfg.study.seeds_per_process)
    why = next((w for c in grid if c.cfg is not None and (w := group_refusal(c.cfg))), None)
    if k > 1 and why:
        log.warning("study.seeds_per_process=%d: one seed per process instead: %s", k, why)
        return 1
    return k


def study(cfg: DictConfig) -> StudyResult:
    """Train, evaluate and report the grid of ``cfg.study`` in ``cfg.study.dir`` (resuming).

    Args:
        cfg: the composed ``study`` config.
    """
    from memrl.checkpoint.opponents import check_pool_views, pool_views
    from memrl.evaluation.protocol import check_protocol, suffixed
    from memrl.report import report, stats_config
    from memrl.schemas import check_train
    from memrl.studies import evaluation as ev
    from memrl.studies.extend import extend, sources
    from memrl.studies.grid import Outcome, cells, run_cells
    from memrl.studies.report import ReportInputs, stage_figure, write_report

    start = time.perf_counter()
    check_study(cfg)
    s = cfg.study
    folder = Path(str(s.dir))
    grid = cells(s, folder / "runs")  # a bad train override stops here, before any write
    protocol = check_protocol(cfg.protocol)
    test_pool = pool_views([str(p) for p in protocol.opponent.get("pool") or []]) \
        if isinstance(protocol.opponent, Mapping) else []
    for cell in grid:
        assert cell.cfg is not None
        check_train(cell.cfg)
        check_pool_views(test_pool, cell.cfg.env)  # the test traffic's agents must know these frames
    settings = ev.EvalSettings(protocol, int(s.workers), int(s.batch), bool(s.progress))
    tag = settings.tag  # test traffic other than constant: folders of its own, report in test_<tag>/
    early = ev.Evaluations()  # made as runs finish (study.evaluate=each); the report reuses them

    def evaluate(cell: Cell, into: ev.Evaluations) -> None:
        ev.evaluate_run(cell.run_dir, settings, into)
        if s.stage1 and by_label(cell.mode).pretrains:
            ev.evaluate_stage1(cell.run_dir, folder / "stage1" / suffixed(cell.name, tag), settings, into)

    def evaluate_early(cell: Cell) -> None:
        try:
            evaluate(cell, early)
        except Exception as err:  # the others train on; the evaluation after training tries again
            log.error("%s: evaluation failed (%s); it is tried again after training", cell.name, err)

    if s.train:
        earlier = sources(grid, Path(str(s.extend_from))) if s.extend_from else []
        check_record(folder, cfg)
        extended = extend(earlier, folder / STUDY_JSON)
        outcome = run_cells(grid, int(s.jobs), finished=evaluate_early if s.evaluate == "each" else None,
                            per_process=seeds_per_process(cfg, grid))
        if s.evaluate == "none":
            return trained_only(cfg, folder, outcome, extended, start)
    else:  # an interim report: the runs finished so far
        extended = []
        outcome = Outcome(skipped=[c.name for c in grid if c.finished()])
        if not outcome.skipped:
            raise config_error("study.train", f"false reports the finished runs of {folder}, and none "
                               "has finished yet (study.status=true shows where they stand)")
        check_record(folder, cfg)
    finished = [c for c in grid if c.finished()]

    out_dir = folder / suffixed("test", tag) if tag else folder
    evals = ev.Evaluations()
    ev.evaluate_runs([c.run_dir for c in finished], settings, evals)  # those left to make: together
    if s.stage1:
        ev.evaluate_stage1s([(c.run_dir, folder / "stage1" / suffixed(c.name, tag)) for c in finished
                             if by_label(c.mode).pretrains], settings, evals)
    baselines = [folder / "baselines" / suffixed(str(b), tag) for b in s.baselines]
    for name, place in zip(s.baselines, baselines, strict=True):
        ev.evaluate_baseline(str(name), grid[0].cfg.env, place, settings, evals)  # type: ignore[union-attr]

    labels = list(dict.fromkeys(c.label for c in finished))
    pairs = comparison_pairs(grid, labels)
    folders = [ev.eval_folder(c.run_dir, settings) for c in finished] + baselines
    result = StudyResult(folder, out_dir / "report.md", out_dir / "table3.csv", outcome.skipped,
                         outcome.trained, outcome.resumed, extended, outcome.failed,
                         early.made + evals.made, [r for r in evals.reused if r not in early.made],
                         command=command_line(cfg))
    if not folders:
        raise RuntimeError(f"study {folder}: no run finished and no baseline to report")
    rcfg = report_config(cfg, folders, labels + [str(b) for b in s.baselines if b == "scripted"], pairs,
                         [c.run_dir for c in finished])
    files = report(rcfg, out_dir=out_dir)
    scfg = stats_config(rcfg)
    switch = stage_figure(finished, evals.runs, evals.stage1, out_dir / "fig_stage2.png", scfg,
                          int(rcfg.curve_resamples))
    result.figures = [f for f in [files.fig5, switch, *files.strips] if f is not None]
    result.wall_s = time.perf_counter() - start
    protocol: dict = OmegaConf.to_container(cfg.protocol, resolve=True)  # type: ignore[assignment]
    write_report(ReportInputs(str(s.name), result.command, grid, finished, outcome.failed, evals.runs,
                              evals.stage1, evals.baselines, protocol, scfg, pairs,
                              result.figures, result.wall_s, variants_of(cfg)), result.report)
    log.info("study %s: %d runs skipped, %d trained, %d resumed, %d failed; %d evaluations made, "
             "%d reused; report in %s", folder, len(result.skipped), len(result.trained),
             len(result.resumed), len(result.failed), len(result.evaluated), len(result.reused),
             result.report)
    print(f"wrote {result.report}")
    return result


def study_status(cfg: DictConfig) -> list[str]:
    """``study.status=true``: where each run of the grid stands (:mod:`memrl.studies.status`)."""
    from memrl.studies.grid import cells
    from memrl.studies.status import status_table

    check_study(cfg)
    folder = Path(str(cfg.study.dir))
    lines = [f"study {cfg.study.name} ({folder})"]
    record = folder / STUDY_JSON
    made = read_record(record).get("train_overrides")
    if made is not None and made != [str(o) for o in cfg.study.train_overrides]:
        lines.append(f"(the study was made with study.train_overrides={made}; the budgets below "
                     "are this call's)")
    return lines + status_table(cells(cfg.study, folder / "runs"))


@hydra.main(version_base="1.3", config_path="conf", config_name="study")
def main(cfg: DictConfig) -> None:
    if cfg.study.status:
        lines = run_task(study_status, cfg)
        if lines is not None:
            print("\n".join(lines))
        return
    result = run_task(study, cfg)
    if result is not None and result.failed:
        print(f"study: {len(result.failed)} runs failed: " + "; ".join(
            f"{k}: {v}" for k, v in result.failed.items()), file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    register_configs()
    run_hydra(main)
