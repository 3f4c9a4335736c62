"""Table III: survival and goal scores per method, mean over seeds with bootstrap intervals.

Each row is one label (Default, A, B, scripted, random, human, ...); its *units* are the
evaluation results of that label (one per training seed, or per person for humans). A cell
is the mean of the units' scores with a percentile-bootstrap confidence interval over units
(``scipy.stats.bootstrap``; rliable's stratified bootstrap reduces to this for one task).
A row with a single unit has no spread over seeds: its interval is over that unit's episodes
instead, and says so (``over = episodes``). Pairwise differences (B - Default, A - Default)
resample both rows independently; an interval that excludes zero is flagged.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import bootstrap

from memrl.evaluation.protocol import INITIAL_LANES
from memrl.evaluation.results import EvalResult

log = logging.getLogger(__name__)

METRICS = ("survival", "goal")
COLUMNS = tuple((lane, metric) for lane in INITIAL_LANES for metric in METRICS)
"""Table III's columns: (initial lane, metric)."""
ROW_ORDER = ("Default", "A", "B", "scripted", "random", "human")
"""Rows in this order first; other labels follow alphabetically."""


@dataclass
class Cell:
    """One (row, column) entry."""

    values: list[float]
    """Per-unit scores (per 100 episodes), in unit order."""
    mean: float
    low: float
    high: float
    over: str
    """What the interval resamples: ``seeds`` (units) or ``episodes`` (a single unit)."""
    episodes: list[int] = field(default_factory=list)
    """Episodes behind each unit's score."""

    def excludes_zero(self) -> bool:
        return bool(self.low > 0 or self.high < 0)


@dataclass
class Row:
    label: str
    units: list[str]
    cells: dict[tuple[str, str], Cell]


@dataclass
class Difference:
    """``a - b`` for one column."""

    a: str
    b: str
    column: tuple[str, str]
    cell: Cell
    n_a: int = 0
    """Units (seeds, people) of row ``a``."""
    n_b: int = 0


@dataclass
class StatsConfig:
    confidence: float = 0.95
    n_resamples: int = 10_000
    seed: int = 0


def _mean_diff(x: np.ndarray, y: np.ndarray, axis: int = -1) -> np.ndarray:
    return np.mean(x, axis=axis) - np.mean(y, axis=axis)


def _interval(samples: Sequence[np.ndarray], statistic, cfg: StatsConfig, key: int) -> tuple[float, float]:
    """Percentile bootstrap interval; degenerate (all equal) samples give a zero-width one."""
    if all(np.ptp(s) == 0 for s in samples):
        value = float(statistic(*[s[None] for s in samples], axis=-1)[0])
        return value, value
    res = bootstrap(tuple(samples), statistic, confidence_level=cfg.confidence,
                    n_resamples=cfg.n_resamples, method="percentile", vectorized=True,
                    rng=np.random.default_rng([cfg.seed, key]))
    return float(res.confidence_interval.low), float(res.confidence_interval.high)


def outcomes(result: EvalResult, lane: str, metric: str) -> np.ndarray:
    """Per-episode outcomes of one unit, scaled to the score (0 or 100 each)."""
    recs = [r for r in result.records() if r.initial_lane == lane]
    return 100.0 * np.array([r.survived if metric == "survival" else r.goal for r in recs], dtype=float)


def _samples(results: list[EvalResult], lane: str, metric: str) -> tuple[np.ndarray, str]:
    """What a cell resamples: units' scores, or the episodes of a single unit."""
    if len(results) >= 2:
        return np.array([getattr(r.scores[lane], f"{metric}_score") for r in results]), "seeds"
    return outcomes(results[0], lane, metric), "episodes"


def make_cell(results: list[EvalResult], lane: str, metric: str, cfg: StatsConfig, key: int) -> Cell:
    values = [float(getattr(r.scores[lane], f"{metric}_score")) for r in results]
    sample, over = _samples(results, lane, metric)
    low, high = _interval([sample], np.mean, cfg, key)
    return Cell(values, float(np.mean(values)), low, high, over,
                [r.scores[lane].episodes for r in results])


def group(results: Sequence[EvalResult]) -> dict[str, list[EvalResult]]:
    """Results by label, labels in :data:`ROW_ORDER` then alphabetically; units sorted."""
    by: dict[str, list[EvalResult]] = {}
    for r in results:
        by.setdefault(r.name, []).append(r)
    order = sorted(by, key=lambda k: (ROW_ORDER.index(k) if k in ROW_ORDER else len(ROW_ORDER), k))
    return {k: sorted(by[k], key=lambda r: _natural(r.unit)) for k in order}


def _natural(text: str) -> tuple:
    """Sort key putting ``seed 2`` before ``seed 10``."""
    return tuple(int(t) if t.isdigit() else t for t in text.replace("_", " ").split())


def check_protocols(results: Sequence[EvalResult]) -> str:
    """The one protocol id all results share; raises naming the odd folders otherwise."""
    ids: dict[str, list[str]] = {}
    for r in results:
        ids.setdefault(r.protocol_id, []).append(str(r.path))
    if len(ids) > 1:
        detail = "; ".join(f"{k}: {v[:3]}{' ...' if len(v) > 3 else ''}" for k, v in ids.items())
        raise ValueError("report: evaluations were made with different protocols (episodes, seeds, "
                         f"cars, duration) and are not comparable: {detail}")
    return next(iter(ids)) if ids else ""


def table(results: Sequence[EvalResult], cfg: StatsConfig | None = None) -> list[Row]:
    """Table III rows (only the columns every unit of a row has)."""
    cfg = cfg or StatsConfig()
    rows = []
    for i, (label, rs) in enumerate(group(results).items()):
        cells = {}
        for j, (lane, metric) in enumerate(COLUMNS):
            if all(lane in r.scores for r in rs):
                cells[(lane, metric)] = make_cell(rs, lane, metric, cfg, key=100 * i + j)
        rows.append(Row(label, [r.unit for r in rs], cells))
    return rows


def differences(results: Sequence[EvalResult], pairs: Sequence[Sequence[str]],
                cfg: StatsConfig | None = None) -> list[Difference]:
    """``a - b`` for each pair of labels present, per column, with a bootstrap interval.

    Over seeds when both rows have at least two units, else over the episodes of each."""
    cfg = cfg or StatsConfig()
    by = group(results)
    out = []
    for k, (a, b) in enumerate(pairs):
        if a not in by or b not in by:
            continue
        ra, rb = by[a], by[b]
        for j, (lane, metric) in enumerate(COLUMNS):
            if not all(lane in r.scores for r in ra + rb):
                continue
            va = [getattr(r.scores[lane], f"{metric}_score") for r in ra]
            vb = [getattr(r.scores[lane], f"{metric}_score") for r in rb]
            if len(ra) >= 2 and len(rb) >= 2:
                xs, over = [np.array(va), np.array(vb)], "seeds"
            else:
                xs = [np.concatenate([outcomes(r, lane, metric) for r in rows]) for rows in (ra, rb)]
                over = "episodes"
            low, high = _interval(xs, _mean_diff, cfg, key=10_000 + 100 * k + j)
            diff = float(np.mean(va) - np.mean(vb))
            out.append(Difference(a, b, (lane, metric), Cell([diff], diff, low, high, over),
                                  len(ra), len(rb)))
    return out
