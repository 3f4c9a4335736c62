"""Does the learner see its crash coming? Measured on an evaluation's own test episodes.

The greedy episodes the scores come from are recorded as they are driven (the runners'
``record``: per step the network's expected Q-values of all actions, the action taken and the
reward; :class:`EpisodeTrace`), and this module reduces them, per initial-lane setting, to a
few numbers that ``eval.json`` keeps under ``crash_sight`` (:func:`summarize`):

- **calibration**: the mean Q(s_t, a_t) of the action taken beside the mean discounted return
  that followed, G_t = sum_k gamma^k r_{t+k} (the run's ``agent.gamma``; a crash ends the sum,
  the time limit cuts it), over the steps 1, 2, 3-5, 6-10, 11-20 and 21-40 before a crash
  (1: the step whose action ended in the crash) and over the survivors' steps far from the
  time limit (:func:`survivor_steps`: steps 1-200 of 300); a network that declares a ``risk``
  output (a crash-risk head) also gets its mean risk of the action taken per group (with a
  risk per action, also the share of steps whose action is not the greedy task action: where
  the critic's mask changed the choice), and its
  **risk calibration** (:func:`risk_calibration`: predicted risk, by bin, against the crashes
  that followed);
- **action gaps**: percentiles 10 / 50 / 90 over the test states of best - second Q, the speed
  gap (max - min over the three speed changes at the greedy curvature change) and the curvature
  gap (likewise), the greedy action's speed change (slower / keep / faster counts), beside the
  fit's TD error on the same test steps: mean |Q(s, a) - (r + gamma max_a' Q(s', a'))| with
  the evaluated weights on both sides, a crash's target its reward alone; the last step of an
  episode cut by the time limit is left out (its next state was never acted on).

Plain functions on arrays (``tests/test_crash_sight.py`` computes each by hand); the reports'
tables are :mod:`memrl.evaluation.sight_tables`. The per-run numbers pool over a row's units
(:func:`pool`): step-weighted means and summed counts, exactly; the percentiles as the mean
over the units of each unit's percentile.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

BINS: tuple[tuple[int, int], ...] = ((1, 1), (2, 2), (3, 5), (6, 10), (11, 20), (21, 40))
"""Steps before a crash, grouped (1: the step whose action ended in the crash)."""
TAIL = 100
"""Survivors' steps this close to the time limit are left out (their G misses at most gamma^TAIL
of the tail); shorter episodes keep their first two thirds (:func:`survivor_steps`)."""
RISK_EDGES = (0.0, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0)
"""Bins of predicted risk for the risk calibration (the last bin includes 1)."""
PERCENTILES = (10, 50, 90)
SPEED = ("slower", "keep", "faster")
"""The speed change of action index ``3 * speed + curvature`` (:data:`memrl.envs.vehicles.ACTIONS`)."""


@dataclass
class EpisodeTrace:
    """What one recorded test episode gives: T steps, A actions."""

    initial_lane: str
    episode: int
    q: np.ndarray
    """The network's expected Q-values of every action at each step's state ``[T, A]``."""
    actions: np.ndarray
    """The action taken at each step ``[T]``."""
    rewards: np.ndarray
    """The reward of each step ``[T]``."""
    crashed: bool
    """The episode ended in a collision (at step T); else it ran to the time limit."""
    risk: np.ndarray | None = None
    """The network's ``risk`` output, per action ``[T, A]`` or per state ``[T]`` (None: no risk head)."""


def discounted_returns(rewards: np.ndarray, gamma: float) -> np.ndarray:
    """G_t = sum_k gamma^k r_{t+k} for every step of one episode, no bootstrap after the last."""
    out = np.zeros(len(rewards), dtype=np.float64)
    g = 0.0
    for t in range(len(rewards) - 1, -1, -1):
        g = float(rewards[t]) + gamma * g
        out[t] = g
    return out


def taken(values: np.ndarray, actions: np.ndarray) -> np.ndarray:
    """``values[t, a_t]`` per step (``values`` ``[T, A]``); a per-state ``[T]`` array as it is."""
    values = np.asarray(values)
    if values.ndim == 1:
        return values.astype(np.float64)
    return values[np.arange(len(actions)), np.asarray(actions, dtype=np.int64)].astype(np.float64)


def survivor_steps(duration: int, tail: int = TAIL) -> int:
    """How many first steps of a survivor's episode count: all but the last ``tail`` (at most a
    third of the episode): 200 of 300."""
    return duration - min(tail, duration // 3)


def bin_name(lo: int, hi: int) -> str:
    return str(lo) if lo == hi else f"{lo}-{hi}"


def td_errors(q: np.ndarray, actions: np.ndarray, rewards: np.ndarray, crashed: bool,
              gamma: float) -> np.ndarray:
    """|Q(s_t, a_t) - (r_t + gamma max_a' Q(s_{t+1}, a'))| per step of one episode; at a crash the
    target is r_t alone; the last step of an episode cut by the time limit is left out."""
    qa = taken(q, actions)
    r = np.asarray(rewards, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    err = np.abs(qa[:-1] - (r[:-1] + gamma * q[1:].max(-1)))
    if crashed and len(qa):
        err = np.append(err, abs(qa[-1] - r[-1]))
    return err


def action_gaps(q: np.ndarray) -> dict[str, np.ndarray]:
    """Per state (``q`` ``[N, A]``): ``best_second`` (the greedy action's Q minus the next best);
    with the 9 actions (3 speed x 3 curvature changes) also ``speed_gap`` (max - min of Q over
    the speed changes at the greedy curvature change), ``curvature_gap`` (over the curvature
    changes at the greedy speed change) and ``speed`` (the greedy speed change: 0 slower,
    1 keep, 2 faster)."""
    q = np.asarray(q, dtype=np.float64)
    top = np.sort(q, axis=-1)
    out = {"best_second": top[:, -1] - top[:, -2]}
    if q.shape[-1] == 9:
        grid = q.reshape(-1, 3, 3)  # [state, speed change, curvature change]
        best = q.argmax(-1)
        speed, curv, i = best // 3, best % 3, np.arange(len(q))
        at_curv, at_speed = grid[i, :, curv], grid[i, speed, :]
        out["speed_gap"] = at_curv.max(-1) - at_curv.min(-1)
        out["curvature_gap"] = at_speed.max(-1) - at_speed.min(-1)
        out["speed"] = speed
    return out


def percentiles(x: np.ndarray) -> list[float] | None:
    """Percentiles 10 / 50 / 90 (numpy's linear interpolation); None for no values."""
    return [round(float(v), 4) for v in np.percentile(x, PERCENTILES)] if len(x) else None


def _mean(x: Sequence[float] | np.ndarray) -> float | None:
    """The mean over the values that are not NaN (a trace without the column); None for none."""
    x = np.asarray(x, dtype=np.float64)
    x = x[~np.isnan(x)]
    return round(float(np.mean(x)), 4) if len(x) else None


def calibration(traces: Sequence[EpisodeTrace], gamma: float, duration: int) -> list[dict[str, Any]]:
    """Per group of steps (:data:`BINS`, then ``survivors``): ``steps`` (its name), ``n`` (steps
    in it), ``q`` (mean Q of the action taken), ``g`` (mean discounted return that followed),
    and ``q_risk`` (mean risk of the action taken) when the traces carry a risk; ``masked`` (the
    share of steps whose action taken is not argmax Q: a risk critic's mask chose another) when
    they carry a risk per action."""
    groups: dict[str, list[np.ndarray]] = {bin_name(*b): [] for b in BINS}
    groups["survivors"] = []
    keep = survivor_steps(duration)
    for tr in traces:
        q, g = taken(tr.q, tr.actions), discounted_returns(tr.rewards, gamma)
        risk = taken(tr.risk, tr.actions) if tr.risk is not None else np.full(len(q), np.nan)
        masked = (np.asarray(tr.actions) != np.asarray(tr.q).argmax(-1)).astype(np.float64) \
            if _per_action(tr) else np.full(len(q), np.nan)
        steps = np.stack([q, g, risk, masked], axis=1)  # [T, 4]
        t = np.arange(len(q))
        if tr.crashed:
            before = len(q) - t
            for lo, hi in BINS:
                groups[bin_name(lo, hi)].append(steps[(before >= lo) & (before <= hi)])
        else:
            groups["survivors"].append(steps[t < keep])
    with_risk = any(tr.risk is not None for tr in traces)
    with_mask = any(_per_action(tr) for tr in traces)
    rows = []
    for name, parts in groups.items():
        arr = np.concatenate(parts) if parts else np.zeros((0, 4))
        row: dict[str, Any] = {"steps": name, "n": len(arr), "q": _mean(arr[:, 0]), "g": _mean(arr[:, 1])}
        if with_risk:
            row["q_risk"] = _mean(arr[:, 2])
        if with_mask:
            row["masked"] = _mean(arr[:, 3])
        rows.append(row)
    return rows


def _per_action(tr: EpisodeTrace) -> bool:
    """The trace carries a risk per action (a critic that can mask actions)."""
    return tr.risk is not None and np.asarray(tr.risk).ndim == 2


def risk_calibration(traces: Sequence[EpisodeTrace], gamma_risk: float,
                     duration: int) -> list[dict[str, Any]]:
    """The crash-risk head against what followed, per bin of its predicted risk of the action
    taken (:data:`RISK_EDGES`): ``n`` steps, ``predicted`` (their mean risk), ``realized`` (the
    mean of what Q_risk estimates, gamma_risk^k for a crash k steps after the step's action, 0
    for none) and ``within`` (the share of steps followed by a crash within the critic's horizon,
    round(1 / (1 - gamma_risk)) steps). Every step of a crashed episode counts; a survivor's
    first :func:`survivor_steps` (its later ones, cut by the time limit, would count a crash
    after the limit as none)."""
    horizon = round(1 / (1 - gamma_risk))
    parts = []
    for tr in traces:
        if tr.risk is None:
            continue
        p = taken(tr.risk, tr.actions)
        if tr.crashed:
            ahead = len(p) - 1 - np.arange(len(p))  # steps after this step's action to the crash
            parts.append(np.stack([p, gamma_risk ** ahead, ahead < horizon], axis=1))
        else:
            p = p[:survivor_steps(duration)]
            parts.append(np.stack([p, np.zeros(len(p)), np.zeros(len(p))], axis=1))
    arr = np.concatenate(parts) if parts else np.zeros((0, 3))
    rows = []
    for k, (lo, hi) in enumerate(zip(RISK_EDGES[:-1], RISK_EDGES[1:], strict=True)):
        last = k == len(RISK_EDGES) - 2
        sel = arr[(arr[:, 0] >= lo) & ((arr[:, 0] <= hi) if last else (arr[:, 0] < hi))]
        rows.append({"risk": f"{lo:g}-{hi:g}", "n": len(sel), "predicted": _mean(sel[:, 0]),
                     "realized": _mean(sel[:, 1]), "within": _mean(sel[:, 2])})
    return rows


def gaps(traces: Sequence[EpisodeTrace], gamma: float) -> dict[str, Any]:
    """The action gaps over every test state of ``traces`` (percentiles 10 / 50 / 90), the greedy
    speed changes (counts), and the TD error over their steps (``td_n`` steps, ``td`` mean)."""
    q = np.concatenate([np.asarray(tr.q, dtype=np.float64) for tr in traces]) if traces else np.zeros((0, 9))
    g = action_gaps(q) if len(q) else {}
    td = np.concatenate([td_errors(tr.q, tr.actions, tr.rewards, tr.crashed, gamma) for tr in traces]) \
        if traces else np.zeros(0)
    out: dict[str, Any] = {"states": len(q), "mean_q": _mean(q.reshape(-1))}
    for key in ("best_second", "speed_gap", "curvature_gap"):
        out[key] = percentiles(g[key]) if key in g else None
    out["greedy_speed"] = {name: int((g["speed"] == k).sum()) for k, name in enumerate(SPEED)} \
        if "speed" in g else None
    out["td_n"], out["td"] = len(td), _mean(td)
    return out


def summarize(traces: Iterable[EpisodeTrace], gamma: float, duration: int,
              gamma_risk: float | None = None) -> dict[str, Any]:
    """``eval.json``'s ``crash_sight``: the settings, then per initial-lane setting its episodes,
    crashes, :func:`calibration` and :func:`gaps`; with ``gamma_risk`` (a crash-risk head's
    discount) and traces that carry a risk, also :func:`risk_calibration`."""
    by_lane: dict[str, list[EpisodeTrace]] = {}
    for tr in traces:
        by_lane.setdefault(tr.initial_lane, []).append(tr)

    def lane_block(trs: list[EpisodeTrace]) -> dict[str, Any]:
        block = {"episodes": len(trs), "crashes": sum(t.crashed for t in trs),
                 "calibration": calibration(trs, gamma, duration), "gaps": gaps(trs, gamma)}
        if gamma_risk is not None and any(t.risk is not None for t in trs):
            block["risk_calibration"] = risk_calibration(trs, gamma_risk, duration)
        return block

    out = {"gamma": gamma, "duration": duration, "survivor_steps": survivor_steps(duration),
           "lanes": {lane: lane_block(trs) for lane, trs in by_lane.items()}}
    if gamma_risk is not None:
        out["gamma_risk"] = gamma_risk
    return out


def _weighted(items: Sequence[tuple[int, float | None]]) -> float | None:
    kept = [(n, v) for n, v in items if n and v is not None]
    total = sum(n for n, _ in kept)
    return round(sum(n * v for n, v in kept) / total, 4) if total else None


def pool(blocks: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Several units' blocks of one initial-lane setting (``crash_sight["lanes"][lane]``) as
    one: episodes, crashes and counts summed (``crashes_per_unit`` listed), means weighted by
    their steps, each percentile the mean over the units' percentiles (``units``: how many)."""
    cal = []
    for k, row in enumerate(blocks[0]["calibration"]):
        rows = [b["calibration"][k] for b in blocks]
        out = {"steps": row["steps"], "n": sum(r["n"] for r in rows)}
        for key in ("q", "g", "q_risk", "masked"):
            if any(key in r for r in rows):
                out[key] = _weighted([(r["n"], r.get(key)) for r in rows])
        cal.append(out)
    gs = [b["gaps"] for b in blocks]
    gap: dict[str, Any] = {"states": sum(g["states"] for g in gs),
                           "mean_q": _weighted([(g["states"], g["mean_q"]) for g in gs])}
    for key in ("best_second", "speed_gap", "curvature_gap"):
        vals = [g[key] for g in gs if g.get(key) is not None]
        gap[key] = [round(float(v), 4) for v in np.mean(vals, axis=0)] if vals else None
    speeds = [g["greedy_speed"] for g in gs if g.get("greedy_speed")]
    gap["greedy_speed"] = {name: sum(s[name] for s in speeds) for name in SPEED} if speeds else None
    gap["td_n"] = sum(g["td_n"] for g in gs)
    gap["td"] = _weighted([(g["td_n"], g["td"]) for g in gs])
    out = {"units": len(blocks), "episodes": sum(b["episodes"] for b in blocks),
           "crashes": sum(b["crashes"] for b in blocks),
           "crashes_per_unit": [b["crashes"] for b in blocks], "calibration": cal, "gaps": gap}
    risky = [b["risk_calibration"] for b in blocks if "risk_calibration" in b]
    if risky:
        out["risk_calibration"] = [
            {"risk": rows[0]["risk"], "n": sum(r["n"] for r in rows),
             **{key: _weighted([(r["n"], r[key]) for r in rows])
                for key in ("predicted", "realized", "within")}}
            for rows in zip(*risky, strict=True)]
    return out
