"""The study's ``report.md``: Table III beside the paper's, the comparisons, mode B's stage 1
against its final weights, the budget, the machine and the wall time.

The numbers come from :mod:`memrl.evaluation.stats` (the same seeded bootstrap as
``memrl.report``), so re-reporting an unchanged study writes the same file except its
wall-time and date lines.
"""

from __future__ import annotations

import json
import os
import platform
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import OmegaConf

from memrl.evaluation import stats, tables
from memrl.evaluation.crashes import crash_section
from memrl.evaluation.periodic import PERIODIC_CSV
from memrl.evaluation.protocol import suffixed, traffic_tag, traffic_type
from memrl.evaluation.results import EvalResult
from memrl.evaluation.sight_tables import sight_section
from memrl.modes import MODES, by_label
from memrl.studies.evaluation import STAGE1_SUFFIX
from memrl.studies.grid import Cell
from memrl.studies.traffic import traffic_section

WALL_PREFIX = "- wall time:"
DATE_PREFIX = "- written:"
"""The lines of ``report.md`` that differ between two reports of the same study."""


@dataclass
class ReportInputs:
    """Everything ``report.md`` says."""

    name: str
    command: str
    cells: list[Cell]
    finished: list[Cell]
    failed: dict[str, str]
    runs: list[EvalResult]
    stage1: list[EvalResult]
    baselines: list[EvalResult]
    protocol: dict[str, Any]
    stats: stats.StatsConfig
    comparisons: list[list[str]]
    figures: list[Path]
    wall_s: float
    variants: dict[str, list[str]] = field(default_factory=dict)
    """``study.variants``: name -> its train overrides ({}: none)."""


def offline_settings(cfg: Any) -> str | None:
    """The ``mode`` key of a run config's offline-stage settings (mode B: ``stage1``); None for
    a mode without an offline stage, or one not declared here."""
    spec = MODES.get(str(cfg.mode.get("name")))
    offline = spec.offline_stage if spec else None
    return offline.settings if offline else None


def _pretrains(mode: object) -> bool:
    """Whether runs of mode name ``mode`` have an offline stage (their stage-1 weights)."""
    return str(mode) in MODES and MODES[str(mode)].pretrains


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``; else what ``platform`` says)."""
    info = Path("/proc/cpuinfo")
    if info.is_file():
        for line in info.read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def machine(cells: Sequence[Cell]) -> str:
    """CPU model, cores and the training device(s)."""
    devices = sorted({str(c.cfg.get("device", "cpu")) if c.cfg is not None else "cpu" for c in cells})
    import torch

    names = []
    for d in devices:
        if d == "auto":  # the trainer's choice: a GPU where there is one
            d = "auto: " + ("cuda" if torch.cuda.is_available() else "cpu")
        if "cuda" in d:
            gpu = torch.cuda.get_device_name() if torch.cuda.is_available() else "no GPU here now"
            names.append(f"{d} ({gpu})")
        else:
            names.append(d)
    return f"{cpu_model()}, {os.cpu_count()} cores; training device: {', '.join(names)}"


def _summary(cell: Cell) -> dict[str, Any]:
    path = cell.run_dir / "summary.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def train_wall(summary: dict[str, Any]) -> float | None:
    """A run's training wall time over all its calls (``train_wall_s``; a run that never
    resumed: ``wall_s``); None when unknown (resumed from a checkpoint that did not record it)."""
    if summary.get("train_wall_s") is not None:
        return float(summary["train_wall_s"])
    if summary.get("resumed_from_episode") is None and "wall_s" in summary:
        return float(summary["wall_s"])
    return None


def _unknown(count: int) -> str:
    return f" ({count} resumed from checkpoints that did not record it: not counted)" if count else ""


def training_total(walls: Sequence[float | None]) -> str:
    """``training 1,234 s (sum over 4 runs)``, naming the runs whose time is unknown."""
    known = [w for w in walls if w is not None]
    if walls and not known:
        return f"training time unknown{_unknown(len(walls))}"
    return f"training {sum(known):,.0f} s (sum over {len(known)} runs){_unknown(len(walls) - len(known))}"


def _yaml(value: Any) -> str:
    return "null" if value is None else str(value)


def _span(values: Sequence[float], unit: str = "") -> str:
    if not values:
        return "\u2014"
    lo, hi = min(values), max(values)
    text = f"{lo:,.0f}" if lo == hi else f"{lo:,.0f}\u2013{hi:,.0f} (mean {np.mean(values):,.0f})"
    return text + unit


def budget(cells: Sequence[Cell], finished: Sequence[Cell]) -> list[str]:
    """The configured budget of the runs and what they measured."""
    set_ = sorted({f"total_frames={_yaml(c.cfg.get('total_frames'))}, "
                   f"total_episodes={_yaml(c.cfg.get('total_episodes'))}"
                   for c in cells if c.cfg is not None})
    sums = [_summary(c) for c in finished]

    def span(key: str, unit: str = "") -> str:
        return _span([s[key] for s in sums], unit)

    walls = [train_wall(s) for s in sums]
    known = [w for w in walls if w is not None]
    lines = [f"- budget per run: {'; '.join(set_)}",
             f"- measured per run ({len(sums)} runs): env steps {span('frames')}, episodes "
             f"{span('episodes')}, updates {span('updates')}, training wall {_span(known, ' s')}"
             f"{_unknown(len(walls) - len(known))}"]
    s1 = [s["stage1"]["updates"] for s in sums if _pretrains(s.get("mode")) and s.get("stage1")]
    if s1:
        lines.append(f"- mode B stage 1: {_span(s1)} updates on the prior knowledge (no env steps)")
    return lines


def _pct(x: float) -> str:
    return f"{x:.0f}"


def _fmt(cell: stats.Cell | None) -> str:
    return "\u2014" if cell is None else tables.fmt_cell(cell, 0.95, per_unit=True)


def stage1_section(inputs: ReportInputs) -> list[str]:
    """Mode B rows: stage-1 weights against the final ones, and the periodic curve per run."""
    if not inputs.stage1:
        return []
    s1_rows = {r.label: r for r in stats.table(inputs.stage1, inputs.stats)}
    final_rows = {r.label: r for r in stats.table(inputs.runs, inputs.stats)}
    lines = ["## Mode B: stage-1 weights against the final weights", "",
             "The stage-1 network (trained on the prior knowledge only, `checkpoints/stage1.pt`) and the "
             "final one, on the same protocol scenes: a drop after the switch to stage 2 shows here. "
             "Mean over seeds [interval] (per-seed values).", "",
             "| row | column | stage 1 | final | final \u2212 stage 1 (per seed) |", "|---|---|---|---|---|"]
    for label, s1 in s1_rows.items():
        final = final_rows.get(label[: -len(STAGE1_SUFFIX)])
        for col in stats.COLUMNS:
            a = s1.cells.get(col)
            b = final.cells.get(col) if final is not None else None
            diff = "\u2014"
            if a is not None and b is not None and len(a.values) == len(b.values):
                diff = ", ".join(f"{y - x:+.0f}" for x, y in zip(a.values, b.values, strict=True))
            lines.append(f"| {label} | {tables.column_name(col)} | {_fmt(a)} | {_fmt(b)} | {diff} |")
    lines += gain_lines(inputs)
    lines += ["", "Periodic evaluation through stage 2 (`eval_periodic.csv`, its own scenes, "
              "non-goal starts, survival / goal per 100 episodes):", "",
              "| run | stage 1 (protocol) | first periodic | lowest periodic goal (env step) | last periodic "
              "| final (protocol) |", "|---|---|---|---|---|---|"]
    finals = {str(r.meta.get("run")): r for r in inputs.runs}
    for r in inputs.stage1:
        run = Path(str(r.meta["run"]))
        periodic = _periodic(run)
        ng = r.scores.get("non_goal")
        f = finals.get(str(run))
        fng = f.scores.get("non_goal") if f is not None else None
        first_s = f"{_pct(ng.survival_score)} / {_pct(ng.goal_score)}" if ng else "\u2014"
        fin = f"{_pct(fng.survival_score)} / {_pct(fng.goal_score)}" if fng else "\u2014"
        if periodic:
            first, last = periodic[0], periodic[-1]
            low = min(periodic, key=lambda x: (x["goal_non_goal"], x["env_steps"]))
            cells = [f"{_pct(first['survival_non_goal'])} / {_pct(first['goal_non_goal'])} "
                     f"(step {first['env_steps']:.0f})",
                     f"{_pct(low['goal_non_goal'])} (step {low['env_steps']:.0f})",
                     f"{_pct(last['survival_non_goal'])} / {_pct(last['goal_non_goal'])} "
                     f"(step {last['env_steps']:.0f})"]
        else:
            cells = ["no periodic evaluation (train with eval.every > 0)", "", ""]
        lines.append(f"| {run.name} | {first_s} | " + " | ".join(cells) + f" | {fin} |")
    return lines + [""]


def gain_lines(inputs: ReportInputs) -> list[str]:
    """Per mode B row: "survived and reached" (non-goal starts) of each seed's stage-1 and final
    weights, on how many seeds the final is higher, and P(final > stage 1)."""
    finals = {str(r.meta.get("run")): r for r in inputs.runs}
    lines = ["", "Survived and reached the target lane in the same episode (non-goal starts, per 100), "
             "each seed's stage-1 weights against its final ones; P(final > stage 1) over the seeds as "
             "two samples (Mann-Whitney U / (n m)) [interval]:", "",
             "| row | stage 1 (per seed) | final (per seed) | final higher | P(final > stage 1) |",
             "|---|---|---|---|---|"]
    for k, row in enumerate(stats.rows_of(inputs.stage1, inputs.stats)):
        pairs = [(r, finals[str(r.meta.get("run"))]) for r in row.results if str(r.meta.get("run")) in finals]
        if not pairs:
            continue
        try:
            before = [stats.survived_and_reached(a) for a, _ in pairs]
            after = [stats.survived_and_reached(b) for _, b in pairs]
        except ValueError:  # no non-goal episodes in this protocol
            continue
        g = stats.gain(before, after, inputs.stats, key=30_000 + k)
        p = "\u2014 (one seed)" if g.p is None else f"{g.p:.2f} [{g.p_low:.2f}, {g.p_high:.2f}]"
        label = row.label[: -len(STAGE1_SUFFIX)] if row.label.endswith(STAGE1_SUFFIX) else row.label
        lines.append(f"| {label} | {', '.join(_pct(x) for x in before)} | "
                     f"{', '.join(_pct(x) for x in after)} | {g.higher} of {len(pairs)} | {p} |")
    return lines if len(lines) > 5 else []


def stage1_end(run: Path) -> dict[str, Any] | None:
    """How a mode B run's stage 1 ended (its ``summary.json``): updates, stop reason, and at
    the check whose weights stage 2 started from (the best drive, else the last check) its
    update, drive counts, held-out agreement and steering recall. None without a stage 1."""
    path = run / "summary.json"
    try:
        s1 = json.loads(path.read_text()).get("stage1") if path.is_file() else None
    except (OSError, ValueError):
        return None
    if not isinstance(s1, dict) or not s1.get("agreements"):
        return None
    agreements, parts, drives = s1["agreements"], s1.get("parts") or [], s1.get("drives") or []
    try:
        cfg = OmegaConf.load(run / "config.yaml")
        episodes = int(cfg.mode[offline_settings(cfg)].drive_episodes)
    except Exception:  # noqa: BLE001 - a run without its config (moved, older) shows counts alone
        episodes = 0
    kept = int(s1.get("best_updates") or 0) or int(s1["updates"])
    i = next((k for k, d in enumerate(drives) if d["updates"] == kept), len(agreements) - 1)
    i = min(i, len(agreements) - 1)  # drives and checks are made together: one of each per check
    return {"updates": int(s1["updates"]), "stop": str(s1.get("stop_reason", "")), "kept": kept,
            "drive": drives[i] if i < len(drives) else None, "drive_episodes": episodes,
            "agreement": float(agreements[i]),
            "steering_recall": (parts[i].get("steering_recall") if i < len(parts) else None)}


def stage1_end_section(runs: Sequence[Path]) -> list[str]:
    """``## Mode B: how stage 1 ended``, one row per run that has a stage 1: :func:`stage1_end`."""
    lines = []
    for run in runs:
        end = stage1_end(run)
        if end is None:
            continue
        drive, n = end["drive"], end["drive_episodes"]
        both = "\u2014" if not drive else f"{drive['both']} of {n}" if n else str(drive["both"])
        recall = "\u2014" if end["steering_recall"] is None else f"{end['steering_recall']:.2f}"
        lines.append(f"| {run.name} | {end['updates']:,} | {end['stop']} | {end['kept']:,} | {both} | "
                     f"{end['agreement']:.2f} | {recall} |")
    if not lines:
        return []
    return ["## Mode B: how stage 1 ended", "",
            "From each run's `summary.json`. Stage 2 started from the weights checked at the "
            "update given (the check that drove best, else the last); at that check: the drives "
            "(scenes of their own) that survived and reached the target, the greedy action's "
            "agreement with the held-out demos, and its recall of their steering actions.", "",
            "| run | updates | stop | weights of update | drives: survived and reached | "
            "held-out agreement | steering recall |", "|---|---|---|---|---|---|---|", *lines, ""]


def both_section(groups: Sequence[Sequence[EvalResult]], cfg: stats.StatsConfig) -> list[str]:
    """Per Table III row (each of ``groups`` split into rows as the table is), the non-goal
    test episodes that both survived and reached the target lane (per 100; the lane change done
    safely, which survival and goal count apart)."""
    lines = []
    for results in groups:
        for g in stats.rows_of(results, cfg):
            units = [(r.unit, [x for x in r.records() if x.initial_lane == "non_goal"]) for r in g.results]
            values = [(u, 100 * sum(x.survived and x.goal for x in recs) / len(recs))
                      for u, recs in units if recs]
            if values:
                per = ", ".join(f"{u}: {v:.0f}" for u, v in values)
                lines.append(f"| {g.label} | {len(values)} | {np.mean([v for _, v in values]):.1f} | {per} |")
    if not lines:
        return []
    return ["## Non-goal starts: survived and reached the target", "",
            "Test episodes from non-goal starts that both survived and reached the target lane, per "
            "100 episodes: mean over units (per-unit values).", "",
            "| row | n | survived and reached | per unit |", "|---|---|---|---|", *lines, ""]


LATE = 0.75
"""Training episodes that end after this share of a run's env steps are its "late" ones."""


def training_episodes(run: Path) -> dict[str, float] | None:
    """A run's training episodes (``episodes.csv``; mode B: stage 2's, stage 1 has none): mean
    length [action steps] over all of them and over the late ones, and the share [%] of the
    late ones that collided and that reached the target lane."""
    import csv

    path = run / "episodes.csv"
    if not path.is_file():
        return None
    with path.open(newline="") as f:
        eps = [{k: float(row[k]) for k in ("env_steps", "length", "collided", "reached_target")}
               for row in csv.DictReader(f)]
    if not eps:
        return None
    late = [e for e in eps if e["env_steps"] > LATE * eps[-1]["env_steps"]] or eps[-1:]

    def mean(rows: list[dict[str, float]], key: str) -> float:
        return float(np.mean([r[key] for r in rows]))

    return {"episodes": len(eps), "length": mean(eps, "length"), "late_length": mean(late, "length"),
            "late_collided": 100 * mean(late, "collided"), "late_reached": 100 * mean(late, "reached_target")}


def training_section(finished: Sequence[Cell]) -> list[str]:
    """Per row: the training episodes' mean length and, late in training, how they ended."""
    rows: dict[str, list[dict[str, float]]] = {}
    for c in finished:
        if (t := training_episodes(c.run_dir)) is not None:
            rows.setdefault(c.label, []).append(t)
    if not rows:
        return []
    late = f"last {100 * (1 - LATE):.0f}% of env steps"
    lines = ["## Training episodes", "",
             f"How the training episodes went (exploration included): mean over seeds (per-seed values); "
             f"“late” are the episodes that ended in the {late}.", "",
             "| row | episodes | mean length [steps] | late: mean length [steps] | late: collided [%] "
             "| late: reached target [%] |", "|---|---|---|---|---|---|"]

    def cell(values: list[float]) -> str:
        return f"{np.mean(values):.1f} ({', '.join(f'{v:.1f}' for v in values)})"

    for label, ts in rows.items():
        lines.append(f"| {label} | {cell([t['episodes'] for t in ts])} | {cell([t['length'] for t in ts])} | "
                     f"{cell([t['late_length'] for t in ts])} | {cell([t['late_collided'] for t in ts])} | "
                     f"{cell([t['late_reached'] for t in ts])} |")
    return lines + [""]


def cost_section(finished: Sequence[Cell]) -> list[str]:
    """``## Training cost``: per finished run its env steps, updates (stage 1's among them; none
    where ``mode.stage1.init`` brought them from another run), training wall time over all its
    calls, and the rates over that time."""
    rows = []
    for c in sorted(finished, key=lambda c: c.name):
        s = _summary(c)
        if not s:
            continue
        wall = train_wall(s)
        settings = offline_settings(c.cfg) if c.cfg is not None else None
        shared = settings is not None and OmegaConf.select(c.cfg, f"mode.{settings}.init") is not None
        s1 = int((s.get("stage1") or {}).get("updates", 0)) if _pretrains(s.get("mode")) and not shared else 0
        dash = "\u2014"
        rates = [dash, dash] if not wall else [f"{int(s[k]) / wall:,.1f}" for k in ("updates", "frames")]
        rows.append(f"| {c.name} | {int(s['frames']):,} | {int(s['updates']):,} | {s1:,} | "
                    f"{dash if wall is None else f'{wall:,.0f}'} | {rates[0]} | {rates[1]} |")
    if not rows:
        return []
    return ["## Training cost", "",
            "Per run, over all its calls (`summary.json`; runs that shared the machine's cores with "
            "other work ran slower than alone):", "",
            "| run | env steps | updates | of them stage 1 | training wall [s] | updates/s | env steps/s |",
            "|---|---|---|---|---|---|---|", *rows, ""]


def _periodic(run: Path) -> list[dict[str, float]]:
    import csv

    path = run / PERIODIC_CSV
    if not path.is_file():
        return []
    with path.open(newline="") as f:
        return [{k: float(v) for k, v in row.items() if v not in ("", None)} for row in csv.DictReader(f)]


def comparisons(inputs: ReportInputs, results: Sequence[EvalResult]) -> list[str]:
    """Differences and P(a > b) of the comparisons, per column and over all columns."""
    diffs = stats.differences(results, inputs.comparisons, inputs.stats)
    if not diffs:
        return []
    pct = f"{100 * inputs.stats.confidence:g}%"
    lines = ["## Comparisons", "",
             f"Difference of the means [{pct} interval] and P(a > b), the probability that a seed of a "
             f"scores above a seed of b, [{pct} interval], over seeds (stratified bootstrap).", "",
             "| comparison | column | difference | P(a > b) |", "|---|---|---|---|"]
    for d in diffs:
        col = "all columns" if d.column == stats.ALL else tables.column_name(d.column)
        over = "\u2020" if d.cell.over == "episodes" else ""
        lines.append(f"| {d.a} \u2212 {d.b} | {col} | {d.cell.mean:+.1f} [{d.cell.low:.1f}, "
                     f"{d.cell.high:.1f}]{over} | {tables.fmt_p(d)} |")
    return lines + ["", tables.verdict(diffs, pct), ""]


def stage_figure(finished: Sequence[Cell], runs: Sequence[EvalResult], stage1: Sequence[EvalResult],
                 path: Path, cfg: stats.StatsConfig, n_resamples: int = 2000) -> Path | None:
    """Mode B's periodic evaluation through stage 2 between the protocol scores (non-goal
    survival, goal) of its stage-1 and final weights (:func:`memrl.evaluation.figures.stage_switch`)."""
    from memrl.evaluation.figures import find_training_runs, stage_switch

    def scores(results: Sequence[EvalResult], suffix: str = "") -> dict[str, list[tuple[float, float]]]:
        out: dict[str, list[tuple[float, float]]] = {}
        for r in results:
            if "non_goal" in r.scores and _pretrains(r.meta.get("mode")):
                s = r.scores["non_goal"]
                out.setdefault(r.name.removesuffix(suffix), []).append((s.survival_score, s.goal_score))
        return out

    b_runs = [c.run_dir for c in finished if by_label(c.mode).pretrains]
    if not b_runs:
        return None
    return stage_switch(find_training_runs(b_runs), scores(stage1, STAGE1_SUFFIX), scores(runs), path,
                        confidence=cfg.confidence, n_resamples=n_resamples)


def traffic_words(opponent: Any) -> str:
    """The protocol's other cars in words: ``constant-speed cars`` or e.g. ``mixed cars (each
    driven by one of 3 past agents with probability 0.5)``."""
    kind = traffic_type(opponent)
    if kind == "constant":
        return "constant-speed cars"
    node = opponent if isinstance(opponent, Mapping) else {}
    pool = len(node.get("pool") or [])
    who = f"one of {pool} past agent{'' if pool == 1 else 's'}" if pool else "past agents"
    if kind == "mixed":
        return f"mixed cars (each driven by {who} with probability {node.get('learned_fraction', '?')})"
    return f"{kind} cars (each driven by {who})"


def write_report(inputs: ReportInputs, path: Path) -> Path:
    """Write ``report.md``."""
    results = [*inputs.runs, *inputs.baselines]
    rows = stats.table(results, inputs.stats)
    p = inputs.protocol
    tag = traffic_tag(p["opponent"])
    names = list(dict.fromkeys(c.variant for c in inputs.cells if c.variant))
    axes = [("variants", names), ("modes", [c.mode for c in inputs.cells]),
            ("traffic", [c.opponent for c in inputs.cells]), ("seeds", [str(c.seed) for c in inputs.cells])]
    grid = " \u00d7 ".join(f"{axis} {', '.join(dict.fromkeys(values))}" for axis, values in axes if values)
    evals = sum(r.wall_s for r in [*results, *inputs.stage1])
    walls = [train_wall(_summary(c)) for c in inputs.finished]
    lines = [f"# Study {inputs.name}: Table III from trained agents", "",
             f"- command: `{inputs.command}`",
             f"- grid: {grid} ({len(inputs.finished)} of {len(inputs.cells)} runs finished); baselines: "
             f"{', '.join(dict.fromkeys(r.name for r in inputs.baselines)) or 'none'}",
             *[f"- variant {k}: `{' '.join(v) or '(no overrides)'}`" for k, v in inputs.variants.items()
               if k in names],
             *budget(inputs.cells, inputs.finished),
             f"- protocol: {p['episodes']} episodes per initial lane ({', '.join(p['initial_lanes'])}), "
             f"{p['vehicles_count'][0]}\u2013{p['vehicles_count'][1]} other cars, {p['duration']} steps, "
             f"scene seed {p['seed']}, {traffic_words(p['opponent'])}",
             f"- machine: {machine(inputs.cells)}",
             f"- total: {training_total(walls)}, evaluation {evals:,.0f} s",
             f"{WALL_PREFIX} {inputs.wall_s:,.0f} s for this call",
             f"{DATE_PREFIX} {time.strftime('%Y-%m-%d %H:%M:%S %Z')}", ""]
    if inputs.failed:
        lines += ["**Failed runs** (not in the table; tracebacks in `runs/<run>/train.log`; the same "
                  "command tries them again):", ""]
        lines += [f"- {name}: {err}" for name, err in inputs.failed.items()] + [""]
    missing = [c.name for c in inputs.cells if c not in inputs.finished and c.name not in inputs.failed]
    if missing:
        lines += [f"Not finished: {', '.join(missing)}.", ""]
    lines += ["## Table III: survival and goal scores (per 100 episodes)", "",
              tables.side_by_side(rows, inputs.stats.confidence), *comparisons(inputs, results),
              *stage1_section(inputs),
              *stage1_end_section([Path(str(r.meta["run"])) for r in inputs.runs if r.meta.get("run")]),
              *both_section([[*inputs.runs, *inputs.baselines], inputs.stage1], inputs.stats),
              *traffic_section([[*inputs.runs, *inputs.baselines], inputs.stage1], inputs.stats),
              *crash_section([[*inputs.runs, *inputs.baselines], inputs.stage1], inputs.stats),
              *sight_section([[*inputs.runs, *inputs.baselines], inputs.stage1], inputs.stats),
              *training_section(inputs.finished), *cost_section(inputs.finished), "## Figures", ""]
    lines += [f"![{f.stem}]({f.name})" for f in inputs.figures] + [""]
    lines += ["## Files", "",
              "`table3.csv` (this table, long format, with the paper's column), `table3.md` and "
              "`differences.csv` (every comparison), `report.json` (all numbers and sources), "
              "`study.json` (the grid), `runs/[<variant>_]<mode>_<traffic>_s<seed>/` (each run and its "
              f"`{suffixed('eval', tag)}/`), "
              f"`stage1/` (mode B's stage-1 evaluations{f', `*_{tag}/`' if tag else ''}), `baselines/`.", ""]
    path.write_text("\n".join(lines))
    return path
