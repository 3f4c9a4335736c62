"""Table III: survival and goal scores per row, mean and IQM over seeds with bootstrap intervals.

Rows are whole configurations (:mod:`~memrl.evaluation.rows`); a row's *units* are its
evaluations (one per training seed, or per person for humans). A cell is one column of
Table III (initial lane x metric), i.e. one task in rliable's terms, and holds, over the
units' scores (:mod:`~memrl.evaluation.bootstrap`):

* the mean and the IQM (``scipy.stats.trim_mean(x, 0.25)``: the mean of the middle 50%;
  with fewer than 4 units it equals the mean), each with a percentile stratified-bootstrap
  interval, which for one column is the ordinary bootstrap over the row's seeds;
* the per-unit values.

A row with a single unit has no spread over seeds: its intervals are over that unit's
episodes instead, and say so (``over = episodes``); its IQM is its score. Pairwise
comparisons (B vs Default, A vs Default) give per column the mean difference and the
probability of improvement P(a > b) (Mann-Whitney U / (n m), ties 1/2) over the seeds of the
two rows, each with an interval resampling both rows independently; and the same over all
columns (:data:`ALL`: the mean difference over every (seed, column) score and the mean over
columns of P(a > b)), with a stratified bootstrap that resamples seeds within each column.
P(a > b) and the aggregate need two units in each row.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from memrl.evaluation import bootstrap as bs
from memrl.evaluation.protocol import INITIAL_LANES
from memrl.evaluation.results import EvalResult
from memrl.evaluation.rows import IGNORED_KEYS, RowGroup, matching_rows, split_rows
from memrl.evaluation.rows import ROW_ORDER as ROW_ORDER  # re-exported (figures)

log = logging.getLogger(__name__)

METRICS = ("survival", "goal")
COLUMNS = tuple((lane, metric) for lane in INITIAL_LANES for metric in METRICS)
"""Table III's columns: (initial lane, metric)."""
ALL = ("all", "columns")
"""The column of a comparison aggregated over every column (rliable's tasks) both rows have."""


@dataclass
class Cell:
    """One (row, column) entry, or one comparison's difference."""

    values: list[float]
    """Per-unit scores (per 100 episodes), in unit order."""
    mean: float
    low: float
    high: float
    over: str
    """What the intervals resample: ``seeds`` (units) or ``episodes`` (a single unit)."""
    episodes: list[int] = field(default_factory=list)
    """Episodes behind each unit's score."""
    iqm: float | None = None
    """Interquartile mean of ``values`` (None for differences)."""
    iqm_low: float | None = None
    iqm_high: float | None = None

    def excludes_zero(self) -> bool:
        return bool(self.low > 0 or self.high < 0)


@dataclass
class Row:
    label: str
    units: list[str]
    cells: dict[tuple[str, str], Cell]
    base: str = ""
    """The evaluations' name (the label without the configuration that differs)."""
    variant: dict = field(default_factory=dict)
    """Config keys where this row differs from other rows of ``base``."""


@dataclass
class Difference:
    """``a - b`` and P(a > b) for one column."""

    a: str
    b: str
    column: tuple[str, str]
    cell: Cell
    n_a: int = 0
    """Units (seeds, people) of row ``a``."""
    n_b: int = 0
    p_improvement: float | None = None
    """P(a > b) over seeds (None when a row has a single unit)."""
    p_low: float | None = None
    p_high: float | None = None


@dataclass
class StatsConfig:
    confidence: float = 0.95
    n_resamples: int = 10_000
    seed: int = 0
    ignore: tuple[str, ...] = IGNORED_KEYS
    """Config keys that never split a row (:data:`~memrl.evaluation.rows.IGNORED_KEYS`)."""

    def rng(self, key: int) -> np.random.Generator:
        """The generator of one interval (independent of the order intervals are computed in)."""
        return np.random.default_rng([self.seed, key])


def _interval(samples: Sequence[np.ndarray], statistic: bs.Statistic, cfg: StatsConfig,
              key: int) -> tuple[float, float]:
    return bs.interval(samples, statistic, cfg.confidence, cfg.n_resamples, cfg.rng(key))


def score(result: EvalResult, lane: str, metric: str) -> float:
    """One unit's score in one column."""
    return float(getattr(result.scores[lane], f"{metric}_score"))


def outcomes(result: EvalResult, lane: str, metric: str) -> np.ndarray:
    """Per-episode outcomes of one unit, scaled to the score (0 or 100 each)."""
    recs = [r for r in result.records() if r.initial_lane == lane]
    return 100.0 * np.array([r.survived if metric == "survival" else r.goal for r in recs], dtype=float)


def make_cell(results: list[EvalResult], lane: str, metric: str, cfg: StatsConfig, key: int) -> Cell:
    """Mean and IQM over the units with intervals (over episodes for a single unit)."""
    values = [score(r, lane, metric) for r in results]
    if len(results) >= 2:
        sample, over = np.array(values), "seeds"
    else:
        sample, over = outcomes(results[0], lane, metric), "episodes"
    low, high = _interval([sample], bs.aggregate_mean, cfg, key)
    if over == "seeds":
        iqm = bs.point([sample], bs.iqm)
        iqm_low, iqm_high = _interval([sample], bs.iqm, cfg, key)  # the same resamples as the mean
    else:  # the IQM of one seed is its score, known as well as the mean is
        iqm, iqm_low, iqm_high = values[0], low, high
    return Cell(values, float(np.mean(values)), low, high, over,
                [r.scores[lane].episodes for r in results], iqm, iqm_low, iqm_high)


def rows_of(results: Sequence[EvalResult], cfg: StatsConfig | None = None) -> list[RowGroup]:
    """The rows (whole configurations) of the results."""
    return split_rows(results, (cfg or StatsConfig()).ignore)


def group(results: Sequence[EvalResult], cfg: StatsConfig | None = None) -> dict[str, list[EvalResult]]:
    """Results by row label (:func:`rows_of` order); units sorted."""
    return {g.label: g.results for g in rows_of(results, cfg)}


def check_protocols(results: Sequence[EvalResult]) -> str:
    """The one protocol id all results share; raises naming the odd folders otherwise."""
    ids: dict[str, list[str]] = {}
    for r in results:
        ids.setdefault(r.protocol_id, []).append(str(r.path))
    if len(ids) > 1:
        detail = "; ".join(f"{k}: {v[:3]}{' ...' if len(v) > 3 else ''}" for k, v in ids.items())
        from memrl.errors import config_error

        raise config_error("runs", "evaluations made under different protocols (episodes, seeds, "
                           f"cars, duration) are not comparable: {detail}; report each protocol's "
                           "folders apart (or evaluate them again under one protocol)")
    return next(iter(ids)) if ids else ""


def table(results: Sequence[EvalResult], cfg: StatsConfig | None = None) -> list[Row]:
    """Table III rows (only the columns every unit of a row has)."""
    cfg = cfg or StatsConfig()
    rows = []
    for i, g in enumerate(rows_of(results, cfg)):
        cells = {}
        for j, (lane, metric) in enumerate(COLUMNS):
            if all(lane in r.scores for r in g.results):
                cells[(lane, metric)] = make_cell(g.results, lane, metric, cfg, key=100 * i + j)
        rows.append(Row(g.label, [r.unit for r in g.results], cells, g.base, dict(g.variant)))
    return rows


def differences(results: Sequence[EvalResult], pairs: Sequence[Sequence[str]],
                cfg: StatsConfig | None = None) -> list[Difference]:
    """``a - b`` and P(a > b) for each pair of rows present, per column, with bootstrap intervals.

    ``a`` and ``b`` are row labels or names (:func:`~memrl.evaluation.rows.matching_rows`).
    Over seeds when both rows have at least two units, else the difference is over the
    episodes of each and P(a > b) is left out."""
    cfg = cfg or StatsConfig()
    groups = rows_of(results, cfg)
    out = []
    matched = [pair for a, b in pairs for pair in matching_rows(groups, a, b)]
    for k, (ga, gb) in enumerate(matched):
        ra, rb = ga.results, gb.results
        for j, (lane, metric) in enumerate(COLUMNS):
            if not all(lane in r.scores for r in ra + rb):
                continue
            va = np.array([score(r, lane, metric) for r in ra])
            vb = np.array([score(r, lane, metric) for r in rb])
            key = 10_000 + 100 * k + j
            p = p_low = p_high = None
            if len(ra) >= 2 and len(rb) >= 2:
                xs, over = [va, vb], "seeds"
                p = bs.point(xs, bs.probability_of_improvement)
                p_low, p_high = _interval(xs, bs.probability_of_improvement, cfg, key)
            else:
                xs = [np.concatenate([outcomes(r, lane, metric) for r in rows]) for rows in (ra, rb)]
                over = "episodes"
            low, high = _interval(xs, bs.mean_difference, cfg, key)
            diff = float(np.mean(va) - np.mean(vb))
            out.append(Difference(ga.label, gb.label, (lane, metric), Cell([diff], diff, low, high, over),
                                  len(ra), len(rb), p, p_low, p_high))
        aggregate = over_all_columns(ra, rb, cfg, key=20_000 + 100 * k)
        if aggregate is not None:
            out.append(Difference(ga.label, gb.label, ALL, *aggregate))
    return out


def over_all_columns(ra: list[EvalResult], rb: list[EvalResult], cfg: StatsConfig,
                     key: int) -> tuple[Cell, int, int, float, float, float] | None:
    """The comparison aggregated over the columns both rows have (rliable's tasks): the mean
    difference over all (seed, column) scores and the mean over columns of P(a > b), with a
    stratified bootstrap (seeds resampled per column, each row independently). None with
    fewer than two seeds in a row or fewer than two columns."""
    cols = [(lane, metric) for lane, metric in COLUMNS if all(lane in r.scores for r in ra + rb)]
    if len(ra) < 2 or len(rb) < 2 or len(cols) < 2:
        return None
    xs = [np.array([[score(r, lane, metric) for lane, metric in cols] for r in rows]) for rows in (ra, rb)]
    diff = bs.point(xs, bs.mean_difference)
    low, high = _interval(xs, bs.mean_difference, cfg, key)
    p = bs.point(xs, bs.probability_of_improvement)
    p_low, p_high = _interval(xs, bs.probability_of_improvement, cfg, key)
    return Cell([diff], diff, low, high, "seeds"), len(ra), len(rb), p, p_low, p_high


def survived_and_reached(result: EvalResult, lane: str = "non_goal") -> float:
    """Episodes of ``lane`` that both survived and reached the target lane, per 100."""
    recs = [r for r in result.records() if r.initial_lane == lane]
    if not recs:
        raise ValueError(f"{result.path}: no {lane} episodes")
    return 100.0 * sum(bool(r.survived and r.goal) for r in recs) / len(recs)


@dataclass
class Gain:
    """One measure before and after (e.g. mode B's stage-1 weights and its final ones), per unit."""

    before: list[float]
    after: list[float]
    higher: int
    """Units whose ``after`` exceeds their own ``before``."""
    p: float | None
    """P(after > before) over the units as two samples (Mann-Whitney U / (n m), ties 1/2);
    None with fewer than two units."""
    p_low: float | None = None
    p_high: float | None = None


def gain(before: Sequence[float], after: Sequence[float], cfg: StatsConfig | None = None,
         key: int = 30_000) -> Gain:
    """:class:`Gain` of paired per-unit values (``before[i]`` and ``after[i]``: the same unit),
    with a bootstrap interval of P(after > before)."""
    cfg = cfg or StatsConfig()
    if len(before) != len(after):
        raise ValueError(f"gain: {len(before)} values before, {len(after)} after")
    higher = sum(a > b for a, b in zip(after, before, strict=True))
    out = Gain(list(before), list(after), higher, None)
    if len(before) >= 2:
        xs = [np.asarray(after, dtype=float), np.asarray(before, dtype=float)]
        out.p = bs.point(xs, bs.probability_of_improvement)
        out.p_low, out.p_high = _interval(xs, bs.probability_of_improvement, cfg, key)
    return out
