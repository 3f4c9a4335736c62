"""Fig. 5: mean return and mean survival steps against training episode, per mode.

Each run's ``episodes.csv`` is smoothed with a trailing moving average; the curves of one
mode (its seeds) are cut to the shortest run, averaged, and shaded with a percentile-bootstrap
interval over seeds at every plotted episode. A third panel shows the periodic evaluation
(``eval_periodic.csv``) when runs have it.
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
from memrl.evaluation.policies import MODE_LABELS, run_config
from memrl.evaluation.stats import ROW_ORDER

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
        out.append(Curves(MODE_LABELS.get(mode, mode), cfg.get("seed"), columns, periodic or None))
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


def _panel(ax, runs: list[Curves], key: str, x_key: str, window: int, confidence: float,
           n_resamples: int, source: str = "episodes") -> None:
    by: dict[str, list[Curves]] = {}
    for r in runs:
        by.setdefault(r.label, []).append(r)
    order = sorted(by, key=lambda k: (ROW_ORDER.index(k) if k in ROW_ORDER else 99, k))
    for i, label in enumerate(order):
        found = [r.columns if source == "episodes" else r.periodic for r in by[label]]
        cols = [c for c in found if c and key in c]
        if not cols:
            continue
        n = min(len(c[key]) for c in cols)
        ys = np.stack([smooth(c[key][:n], window) for c in cols])
        x = cols[0][x_key][:n]
        step = max(1, n // MAX_POINTS)
        ys, x = ys[:, ::step], x[::step]
        lo, hi = band(ys, confidence, n_resamples, seed=i)
        color = f"C{i}"
        ax.plot(x, ys.mean(axis=0), color=color, label=f"{label} (n={len(cols)})")
        if len(cols) > 1:
            ax.fill_between(x, lo, hi, color=color, alpha=0.25, linewidth=0)


def learning_curves(runs: list[Curves], path: Path, *, window: int = 10, confidence: float = 0.95,
                    n_resamples: int = 2000) -> Path | None:
    """Write Fig. 5 (and the periodic-evaluation panel when any run has one) to ``path``."""
    if not runs:
        log.info("fig. 5: no training runs (episodes.csv + config.yaml) found; skipped")
        return None
    periodic = any(r.periodic for r in runs)
    fig = Figure(figsize=(15 if periodic else 10, 4), layout="constrained")
    FigureCanvasAgg(fig)  # no pyplot: no global state, no GUI backend
    axes = fig.subplots(1, 3 if periodic else 2)
    specs = [("return", "(a) mean return"), ("survival_steps", "(b) mean survival steps")]
    for ax, (key, title) in zip(axes, specs, strict=False):
        _panel(ax, runs, key, "episode", window, confidence, n_resamples)
        ax.set(title=title, xlabel="training episode")
        ax.grid(alpha=0.3)
    if periodic:
        ax = axes[2]
        _panel(ax, runs, "survival_non_goal", "episode", 1, confidence, n_resamples, source="periodic")
        ax.set(title="(c) periodic evaluation: non-goal survival", xlabel="training episode",
               ylabel="per 100 episodes")
        ax.grid(alpha=0.3)
    axes[0].legend()
    pct = f"{100 * confidence:g}%"
    fig.suptitle(f"Training curves: mean over seeds, smoothed over {window} episodes, "
                 f"shaded {pct} bootstrap interval over seeds", fontsize=10)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    return path
