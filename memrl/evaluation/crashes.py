"""Crash diagnostics of evaluation episodes: how many of each kind, how fast, among how many cars.

Each collided :class:`~memrl.evaluation.protocol.EpisodeRecord` carries the kind and closing
speed of its crash (:mod:`memrl.envs.crash`, the same in both engines) and the number of other
cars in its scene; :mod:`memrl.evaluation.crash_counts` counts them (``eval.json``), and
:func:`crash_section` makes the evaluation and study reports' table: one line per Table III
row and kind, pooled over the row's units and both initial-lane settings.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from memrl.envs.crash import CRASH_KINDS
from memrl.evaluation import stats
from memrl.evaluation.crash_counts import summary
from memrl.evaluation.results import EvalResult


def _row_lines(label: str, s: dict[str, Any], cars: list[int]) -> list[str]:
    lines = []
    for kind in CRASH_KINDS:
        k = s["by_kind"][kind]
        if not k["count"]:
            continue
        speed = f"{k['mean_closing']:.2f} / {k['median_closing']:.2f}" if k["mean_closing"] is not None \
            else "\u2014"
        lines.append(f"| {label} | {kind} | {k['count']} | {k['before_target']} | {speed} | "
                     + " | ".join(str(k["by_cars"].get(str(c), 0)) for c in cars) + " |")
    if not lines:
        lines.append(f"| {label} | none | 0 | 0 | \u2014 | " + " | ".join("0" for _ in cars) + " |")
    return lines


def crash_section(groups: Sequence[Sequence[EvalResult]], cfg: stats.StatsConfig) -> list[str]:
    """Markdown: per Table III row (each of ``groups`` split into rows as the table is), crashes
    by kind, mean / median closing speed, and crashes by number of other cars, pooled over the
    row's units and initial-lane settings. Empty when no result has crash records."""
    rows = []
    for results in groups:
        for g in stats.rows_of(results, cfg):
            recs = [x for r in g.results for x in r.records()]
            if recs:
                rows.append((g.label, summary(recs)))
    if not rows or not any(s["crashes"] for _, s in rows):
        return []
    cars = sorted({int(c) for _, s in rows for k in s["by_kind"].values() for c in k["by_cars"]})
    heads = [f"{c} car{'' if c == 1 else 's'}" for c in cars]
    lines = ["## Crashes by kind", "",
             "Collisions classified from the state at the crash (`memrl.envs.crash`): `ahead` (ran "
             "into the car ahead), `behind` (hit from behind), `side` (side contact), `road_edge`; "
             "of them before the target lane was reached (waiting for a gap or changing lanes); "
             "closing speed [m/s] mean / median (toward the other car along the road; for the edge, "
             "the lateral speed), crashes by the number of other cars; pooled over the row's units "
             "and both initial-lane settings (episodes in brackets).", "",
             "| row | kind | crashes | before target lane | closing mean / median | "
             + " | ".join(heads) + " |",
             "|---|---|---|---|---|" + "---|" * len(cars)]
    for label, s in rows:
        lines += _row_lines(f"{label} ({s['episodes']})", s, cars)
    return lines + [""]
