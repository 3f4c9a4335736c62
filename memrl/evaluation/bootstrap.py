"""rliable's statistics (Agarwal et al. 2021): IQM, stratified bootstrap, probability of improvement.

Scores are arrays ``[runs, tasks]`` (a 1-D array is one task). In Table III a *run* is a
training seed (or a person) and a *task* is a column (initial lane x metric); a cell of the
table is one task, so its stratified bootstrap is the ordinary bootstrap over seeds.

Written with numpy/scipy rather than ``rliable``: ``pip install rliable`` pulls in arch,
statsmodels, seaborn and formulaic for these few functions.

* :func:`iqm`: the interquartile mean, ``scipy.stats.trim_mean(x, 0.25)`` over all runs and
  tasks (rliable's ``aggregate_iqm``). ``trim_mean`` cuts ``floor(n / 4)`` scores from each
  end, so with fewer than 4 scores the IQM is the mean.
* :func:`stratified_resamples`: each task's runs resampled with replacement, independently
  per task (rliable's ``StratifiedBootstrap``; resampled scores of one task stay that task's).
* :func:`interval`: the percentile bootstrap interval of a statistic of one or more score
  arrays, each resampled independently and stratified over tasks (rliable's
  ``StratifiedIndependentBootstrap`` for two rows).
* :func:`probability_of_improvement`: P(X > Y), the Mann-Whitney U statistic of X against Y
  divided by ``n * m`` per task (pairs with X > Y count 1, ties 1/2), averaged over tasks.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from scipy.stats import mannwhitneyu, trim_mean

Statistic = Callable[..., np.ndarray]
"""Maps score arrays ``[..., runs, tasks]`` to values ``[...]`` (leading axes: resamples)."""


def as_scores(x: np.ndarray | Sequence[float]) -> np.ndarray:
    """Scores as a float array ``[runs, tasks]`` (a 1-D array is one task)."""
    a = np.asarray(x, dtype=float)
    if a.ndim == 1:
        a = a[:, None]
    if a.ndim != 2 or a.shape[0] == 0:
        raise ValueError(f"scores must be [runs, tasks] with at least one run, got shape {a.shape}")
    return a


def aggregate_mean(x: np.ndarray) -> np.ndarray:
    """Mean over runs and tasks."""
    return np.mean(x, axis=(-2, -1))


def iqm(x: np.ndarray) -> np.ndarray:
    """Interquartile mean over runs and tasks: the mean of the middle 50% of the scores."""
    flat = x.reshape(*x.shape[:-2], -1)
    return np.asarray(trim_mean(flat, 0.25, axis=-1))


def mean_difference(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Mean of X minus mean of Y."""
    return aggregate_mean(x) - aggregate_mean(y)


def probability_of_improvement(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """P(X > Y): per task U / (n * m) (ties count 1/2), averaged over tasks."""
    n, m = x.shape[-2], y.shape[-2]
    u = mannwhitneyu(x, y, axis=-2, method="asymptotic").statistic  # U of X, [..., tasks]
    return np.mean(np.asarray(u) / (n * m), axis=-1)


def stratified_resamples(scores: np.ndarray, n_resamples: int, rng: np.random.Generator) -> np.ndarray:
    """``[n_resamples, runs, tasks]``: per resample and task, ``runs`` runs drawn with
    replacement from that task's runs (independent draws for every task)."""
    runs, tasks = scores.shape
    idx = rng.integers(0, runs, size=(n_resamples, runs, tasks))
    return scores[idx, np.arange(tasks)]


def percentile_interval(values: np.ndarray, confidence: float) -> tuple[float, float]:
    """The central ``confidence`` interval of bootstrap values (linear-interpolated percentiles)."""
    tail = 100.0 * (1.0 - confidence) / 2.0
    low, high = np.percentile(values, [tail, 100.0 - tail])
    return float(low), float(high)


def interval(samples: Sequence[np.ndarray | Sequence[float]], statistic: Statistic, confidence: float,
             n_resamples: int, rng: np.random.Generator) -> tuple[float, float]:
    """Percentile stratified-bootstrap interval of ``statistic(*samples)``.

    Every sample (``[runs, tasks]``) is resampled on its own (samples drawn in order from
    ``rng``), stratified over tasks; all samples must have the same tasks."""
    arrays = [as_scores(s) for s in samples]
    if len({a.shape[1] for a in arrays}) != 1:
        raise ValueError(f"samples have different numbers of tasks: {[a.shape for a in arrays]}")
    resampled = [stratified_resamples(a, n_resamples, rng) for a in arrays]
    return percentile_interval(statistic(*resampled), confidence)


def point(samples: Sequence[np.ndarray | Sequence[float]], statistic: Statistic) -> float:
    """``statistic`` of the samples themselves."""
    return float(statistic(*[as_scores(s) for s in samples]))
