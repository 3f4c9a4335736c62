"""Fig. 5: return and survival against env steps, per row; mode B's stage switch.

Each run's ``episodes.csv`` is smoothed with a trailing moving average over episodes and drawn
against its env steps, faintly, to its own end. The mean over the runs of a row is taken on a
common grid of env steps, counting each run only up to its end (:func:`pool`), and shaded with
a percentile-bootstrap interval over the runs present; where a run ends the figure says how
many remain (``n=k``). Two more panels show the periodic evaluation (``eval_periodic.csv``:
non-goal survival and goal) when runs have it. :func:`stage_switch` draws mode B's periodic
evaluation through stage 2 between the protocol scores of its stage-1 and final weights.
"""

from __future__ import annotations

import csv
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from memrl.evaluation.periodic import PERIODIC_CSV
from memrl.evaluation.policies import run_config, run_label
from memrl.evaluation.rows import row_rank
from memrl.modes import MODES

log = logging.getLogger(__name__)

MAX_POINTS = 1000
"""Plotted points per curve at most (long runs are subsampled after smoothing)."""


@dataclass
class Curves:
    """The training records of one run."""

    label: str
    seed: int | None
    columns: dict[str, np.ndarray]
    """episodes.csv columns as float arrays."""
    periodic: dict[str, np.ndarray] | None = None
    mode: str = "default"
    run: Path | None = None


def _read_csv(path: Path) -> dict[str, np.ndarray]:
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        return {}
    out = {}
    for key in rows[0]:
        try:
            out[key] = np.array([float(r[key]) for r in rows])
        except ValueError:
            continue  # text columns (stage)
    return out


def find_training_runs(paths: Sequence[str | Path]) -> list[Curves]:
    """Runs (folders with ``episodes.csv`` and ``config.yaml``) at or below ``paths``."""
    found: list[Path] = []
    for item in paths:
        p = Path(item)
        found += [p] if (p / "episodes.csv").is_file() and (p / "config.yaml").is_file() else \
            sorted(f.parent for f in p.glob("**/episodes.csv") if (f.parent / "config.yaml").is_file())
    out = []
    for run in dict.fromkeys(f.resolve() for f in found):
        cfg = run_config(run)
        if "mode" not in cfg:  # not a training run (e.g. a dataset or an evaluation folder)
            continue
        mode = str(cfg["mode"].get("name", "default"))
        columns = _read_csv(run / "episodes.csv")
        if not columns:
            continue
        periodic = _read_csv(run / PERIODIC_CSV) if (run / PERIODIC_CSV).is_file() else None
        out.append(Curves(run_label(cfg), cfg.get("seed"), columns, periodic or None, mode, run))
    return out


def smooth(values: np.ndarray, window: int) -> np.ndarray:
    """Trailing moving average; the first points average what there is so far."""
    # Hand-written: numpy has no rolling mean with a growing start (pandas' min_periods=1).
    if window <= 1:
        return values.astype(float)
    c = np.cumsum(np.insert(values.astype(float), 0, 0.0))
    n = np.arange(1, len(values) + 1)
    lo = np.maximum(n - window, 0)
    return (c[n] - c[lo]) / (n - lo)


def band(curves: np.ndarray, confidence: float, n_resamples: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Percentile-bootstrap interval over seeds (rows) at every column of ``curves``."""
    if curves.shape[0] < 2:
        return curves[0], curves[0]
    # Hand-written (not scipy.stats.bootstrap): one shared index draw for all columns keeps
    # memory at n_resamples x columns instead of a copy of the data per resample.
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, curves.shape[0], size=(n_resamples, curves.shape[0]))
    means = curves[idx].mean(axis=1)
    alpha = (1 - confidence) / 2
    return np.quantile(means, alpha, axis=0), np.quantile(means, 1 - alpha, axis=0)


@dataclass
class Pooled:
    """Runs of one label on a common x grid: each run counts up to its own end."""

    x: np.ndarray
    mean: np.ndarray
    low: np.ndarray
    high: np.ndarray
    n: np.ndarray
    """Runs that reach each x."""


def pool(xs: Sequence[np.ndarray], ys: Sequence[np.ndarray], confidence: float = 0.95,
         n_resamples: int = 2000, seed: int = 0, points: int = 400) -> Pooled:
    """Mean and percentile-bootstrap interval over the runs at each point of a common grid
    from the first run's start to the last run's end; a run counts from the start (its first
    value before its first point) up to its own end (linear interpolation between its points),
    so ``n`` drops where a shorter run ends."""
    lo_x = min(float(x[0]) for x in xs)
    hi_x = max(float(x[-1]) for x in xs)
    grid = np.unique(np.concatenate([np.linspace(lo_x, hi_x, points), [float(x[-1]) for x in xs]]))
    values = np.full((len(xs), len(grid)), np.nan)
    for i, (x, y) in enumerate(zip(xs, ys, strict=True)):
        inside = grid <= x[-1]
        values[i, inside] = np.interp(grid[inside], x, y)
    have = ~np.isnan(values)
    n = have.sum(axis=0)
    mean = np.where(n > 0, np.nansum(values, axis=0) / np.maximum(n, 1), np.nan)
    low, high = mean.copy(), mean.copy()
    # one bootstrap per set of runs present (the sets change only where a run ends)
    for mask in {tuple(m) for m in have.T if m.sum() >= 2}:
        cols = np.all(have.T == np.array(mask), axis=1)
        rows = np.array(mask)
        low[cols], high[cols] = band(values[rows][:, cols], confidence, n_resamples, seed)
    return Pooled(grid, mean, low, high, n)


def _panel(ax, runs: list[Curves], key: str, x_key: str, window: int, confidence: float,
           n_resamples: int, source: str = "episodes") -> None:
    """Per label: each run faint to its own end, the mean over the runs present with its
    band, and ``n=k`` where runs end."""
    by: dict[str, list[Curves]] = {}
    for r in runs:
        by.setdefault(r.label, []).append(r)
    order = sorted(by, key=row_rank)
    for i, label in enumerate(order):
        found = [r.columns if source == "episodes" else r.periodic for r in by[label]]
        cols = [c for c in found if c and key in c and len(c[key])]
        if not cols:
            continue
        xk = x_key if all(x_key in c for c in cols) else "episode"
        xs = [c[xk] for c in cols]
        ys = [smooth(c[key], window) for c in cols]
        color = f"C{i}"
        for x, y in zip(xs, ys, strict=True):
            step = max(1, len(x) // MAX_POINTS)
            ax.plot(x[::step], y[::step], color=color, alpha=0.25, linewidth=0.8)
        p = pool(xs, ys, confidence, n_resamples, seed=i)
        ax.plot(p.x, p.mean, color=color, linewidth=1.8, label=f"{label} (n={int(p.n.max())})")
        if p.n.max() > 1:
            ax.fill_between(p.x, p.low, p.high, where=p.n >= 2, color=color, alpha=0.2, linewidth=0)
        for j, n in drops(p.x, p.n):  # runs end: the mean goes on with fewer
            ax.axvline(p.x[j], color=color, linestyle=":", linewidth=0.8)
            ax.annotate(f"n={n}", (p.x[j], p.mean[j]), xytext=(3, 6),
                        textcoords="offset points", fontsize=7, color=color)


def drops(x: np.ndarray, n: np.ndarray, merge: float = 0.02) -> list[tuple[int, int]]:
    """Where the number of runs drops, as (index, runs left after it); drops closer than
    ``merge`` of the x range to the first of their group are one mark with the group's last n
    (runs of one budget end within a few env steps of each other)."""
    out: list[tuple[int, int]] = []
    span = float(x[-1] - x[0]) if len(x) else 0.0
    for j in np.flatnonzero(np.diff(n) < 0):
        if out and x[j] - x[out[-1][0]] <= merge * span:
            out[-1] = (out[-1][0], int(n[j + 1]))
        else:
            out.append((int(j), int(n[j + 1])))
    return out


def learning_curves(runs: list[Curves], path: Path, *, window: int = 10, confidence: float = 0.95,
                    n_resamples: int = 2000) -> Path | None:
    """Write Fig. 5 (and the periodic-evaluation panels, non-goal survival and goal, when any
    run has one) to ``path``."""
    if not runs:
        log.info("fig. 5: no training runs (episodes.csv + config.yaml) found; skipped")
        return None
    periodic = any(r.periodic for r in runs)
    fig = Figure(figsize=(20 if periodic else 10, 4), layout="constrained")
    FigureCanvasAgg(fig)  # no pyplot: no global state, no GUI backend
    axes = fig.subplots(1, 4 if periodic else 2)
    specs = [("return", "(a) return", "return [reward per episode]"),
             ("survival_steps", "(b) survival", "survival [action steps per episode]")]
    for ax, (key, title, ylabel) in zip(axes, specs, strict=False):
        _panel(ax, runs, key, "env_steps", window, confidence, n_resamples)
        ax.set(title=title, xlabel="env steps (agent actions)", ylabel=ylabel)
        ax.grid(alpha=0.3)
    if periodic:  # the greedy agent's non-goal survival and goal at the periodic checks
        for ax, (key, title, what) in zip(axes[2:], [("survival_non_goal", "(c)", "survival"),
                                                     ("goal_non_goal", "(d)", "goal")], strict=True):
            _panel(ax, runs, key, "env_steps", 1, confidence, n_resamples, source="periodic")
            ax.set(title=f"{title} periodic evaluation: non-goal {what}",
                   xlabel="env steps (agent actions)", ylabel=f"{what} [% of episodes]")
            ax.grid(alpha=0.3)
    axes[0].legend()
    pct = f"{100 * confidence:g}%"
    fig.suptitle(f"Training curves: mean over seeds (each seed faint, to its own end), smoothed over "
                 f"{window} episodes, shaded {pct} bootstrap interval over seeds; n: seeds still "
                 "running", fontsize=10)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    return path


def stage_switch(runs: list[Curves], stage1: dict[str, list[tuple[float, float]]],
                 final: dict[str, list[tuple[float, float]]], path: Path, *, confidence: float = 0.95,
                 n_resamples: int = 2000) -> Path | None:
    """Mode B through stage 2: the periodic evaluation (non-goal survival and goal) against
    env steps, between the protocol scores of the stage-1 weights (at 0 env steps, where stage
    2 starts) and of the final weights (at the runs' mean end); a drop after the switch shows.

    Args:
        runs: training runs; those of mode B with ``eval_periodic.csv`` are drawn.
        stage1: per row label, the (non-goal survival, non-goal goal) protocol scores of each
            seed's stage-1 weights.
        final: the same for the final weights.
    """
    b = [r for r in runs if r.mode in MODES and MODES[r.mode].pretrains and r.periodic]
    if not b:
        log.info("stage-switch figure: no mode B run with a periodic evaluation; skipped")
        return None
    fig = Figure(figsize=(10, 4), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 2)
    for k, (ax, key, name) in enumerate(zip(axes, ("survival_non_goal", "goal_non_goal"),
                                            ("survival", "goal"), strict=True)):
        _panel(ax, b, key, "env_steps", 1, confidence, n_resamples, source="periodic")
        labels = sorted({r.label for r in b})
        for i, label in enumerate(labels):
            ends = [float(r.periodic["env_steps"][-1]) for r in b if r.label == label and r.periodic]
            points = ((0.0, stage1.get(label, []), "s", "stage-1 weights"),
                      (float(np.mean(ends)), final.get(label, []), "D", "final weights"))
            for x, scores, marker, what in points:
                if not scores:
                    continue
                v = np.array([s[k] for s in scores])
                ax.errorbar([x], [v.mean()], yerr=[[v.mean() - v.min()], [v.max() - v.mean()]], fmt=marker,
                            color=f"C{i}", capsize=3, markersize=6,
                            label=f"{label}: protocol, {what} (mean, min\u2013max)" if k == 0 else None)
        ax.set(title=f"non-goal {name} through stage 2", xlabel="stage-2 env steps (agent actions)",
               ylabel=f"{name} [% of episodes]", ylim=(-5, 105))
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle("Mode B after the switch: periodic evaluation (its own scenes; lines), protocol scores of "
                 "the stage-1 and final weights (markers)", fontsize=10)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    return path
