"""The study report's non-goal scores by the number of other cars in the scene.

Table III pools scenes with 0 to 5 other cars; this splits them, so a row that fails can be
read: an agent that survives every empty road and few crowded ones changes lanes but does not
avoid cars; one that never reaches the target, whatever the traffic, never changes lanes.
Episodes are pooled over a row's units (about 100 / 6 scenes per count and unit is too few for
per-unit values).
"""

from __future__ import annotations

from collections.abc import Sequence

from memrl.evaluation import stats
from memrl.evaluation.results import EvalResult


def by_cars(results: Sequence[EvalResult]) -> dict[int, tuple[int, float, float]]:
    """Other cars -> (episodes, survival [%], goal [%]) of the non-goal episodes of ``results``,
    pooled."""
    counts: dict[int, list[int]] = {}
    for r in results:
        for x in r.records():
            if x.initial_lane == "non_goal" and x.vehicles >= 0:
                c = counts.setdefault(x.vehicles, [0, 0, 0])
                c[0] += 1
                c[1] += x.survived
                c[2] += x.goal
    return {k: (n, 100 * s / n, 100 * g / n) for k, (n, s, g) in sorted(counts.items())}


def traffic_section(groups: Sequence[Sequence[EvalResult]], cfg: stats.StatsConfig) -> list[str]:
    """Per Table III row (each of ``groups`` split into rows as the table is): non-goal survival
    and goal per number of other cars, pooled over the row's units."""
    rows = [(g.label, by_cars(g.results)) for results in groups for g in stats.rows_of(results, cfg)]
    rows = [(label, cells) for label, cells in rows if cells]
    if not rows:
        return []
    cars = sorted({k for _, cells in rows for k in cells})
    heads = [f"{k} car{'' if k == 1 else 's'}" for k in cars]
    lines = ["## Non-goal starts by traffic", "",
             "Survival / goal per 100 non-goal test episodes, split by the number of other cars in "
             "the scene, pooled over the row's units (episodes in brackets).", "",
             "| row | " + " | ".join(heads) + " |", "|---|" + "---|" * len(cars)]
    for label, cells in rows:
        lines.append(f"| {label} | " + " | ".join(
            f"{cells[k][1]:.0f} / {cells[k][2]:.0f} ({cells[k][0]})" if k in cells else "\u2014"
            for k in cars) + " |")
    return lines + [""]
