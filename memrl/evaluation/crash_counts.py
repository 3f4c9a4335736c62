"""Crash counts of evaluation episodes (``eval.json``'s ``crashes``): how many of each kind, how
fast, among how many cars (the report's table: :mod:`memrl.evaluation.crashes`)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

from memrl.envs.crash import CRASH_KINDS
from memrl.evaluation.protocol import INITIAL_LANES, EpisodeRecord


def summary(records: Iterable[EpisodeRecord]) -> dict[str, Any]:
    """Crashes of ``records``: ``episodes``, ``crashes``, and per kind ``count``,
    ``before_target`` (of them, crashes before the target lane was reached: while waiting for a
    gap or changing lanes), ``mean_closing``, ``median_closing`` [m/s] (None without crashes) and
    ``by_cars`` (other cars -> crashes)."""
    recs = list(records)
    crashed = [r for r in recs if r.collided and r.crash_kind]
    kinds: dict[str, Any] = {}
    for kind in CRASH_KINDS:
        mine = [r for r in crashed if r.crash_kind == kind]
        speeds = [r.closing_speed for r in mine if r.closing_speed is not None]
        cars: dict[int, int] = {}
        for r in mine:
            cars[r.vehicles] = cars.get(r.vehicles, 0) + 1
        kinds[kind] = {"count": len(mine), "before_target": sum(not r.reached_target for r in mine),
                       "mean_closing": round(float(np.mean(speeds)), 4) if speeds else None,
                       "median_closing": round(float(np.median(speeds)), 4) if speeds else None,
                       "by_cars": {str(k): cars[k] for k in sorted(cars)}}
    return {"episodes": len(recs), "crashes": len(crashed), "by_kind": kinds}


def by_lane(records: Iterable[EpisodeRecord]) -> dict[str, dict[str, Any]]:
    """:func:`summary` per initial-lane setting (``eval.json``'s ``crashes``)."""
    recs = list(records)
    return {lane: summary(r for r in recs if r.initial_lane == lane)
            for lane in INITIAL_LANES if any(r.initial_lane == lane for r in recs)}
