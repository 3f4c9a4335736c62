"""Deploy metrics: lane-change success, overshoot, tracking and estimation errors.

* ``success``: the true car reached the target lane (all four corners inside it, the env's
  ``reached_target``) and never collided.
* ``overshoot`` [m]: how far the true centre of gravity went beyond the target lane's centre
  line, in the direction of the lane change (0 when it never crossed it). Only for episodes
  that start outside the target lane.
* tracking RMS: true speed [m/s] and curvature [rad/m] of the vehicle model minus the agent's
  commands (the PID set points), over every control period.
* estimate vs raw: RMS error of the EKF's estimate and of the raw sensor readings against the
  truth: position (GNSS fix vs estimate, Euclidean [m]), lateral position [m], speed (wheel
  speed), yaw rate (gyro) and curvature (gyro / wheel speed). Raw GNSS errors are taken at the
  fixes, the others at every control period. ``heading_est``: the filter's heading against the
  true yaw angle (no sensor reads it).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from memrl.control.episode import EpisodeRecord

ERROR_PAIRS = {
    "speed": ("est_speed", "raw_speed", "speed"),
    "yaw_rate": ("est_yaw_rate", "raw_yaw_rate", "yaw_rate"),
    "curvature": ("est_curvature", "raw_curvature", "curvature"),
}
"""Quantity -> (estimate key, raw sensor key, truth key) in the trace."""


def _sq_errors(rec: EpisodeRecord) -> dict[str, np.ndarray]:
    """Squared errors per sample, by metric name."""
    t, g = rec.trace, rec.trace["gnss"]
    out = {
        "speed_tracking": (t["speed"] - t["cmd_speed"]) ** 2,
        "curvature_tracking": (t["curvature"] - t["cmd_curvature"]) ** 2,
        "position_est": (t["est_x"] - t["x"]) ** 2 + (t["est_y"] - t["y"]) ** 2,
        "position_raw": (g[:, 1] - g[:, 3]) ** 2 + (g[:, 2] - g[:, 4]) ** 2,
        "lateral_est": (t["est_y"] - t["y"]) ** 2,
        "lateral_raw": (g[:, 2] - g[:, 4]) ** 2,
        "heading_est": (t["est_heading"] - t["heading"]) ** 2,
    }
    for name, (est, raw, truth) in ERROR_PAIRS.items():
        out[f"{name}_est"] = (t[est] - t[truth]) ** 2
        out[f"{name}_raw"] = (t[raw] - t[truth]) ** 2
    return out


def _rms(sq: np.ndarray) -> float:
    return float(np.sqrt(sq.mean())) if sq.size else math.nan


def changes_lane(rec: EpisodeRecord) -> bool:
    """Whether the episode started outside the target lane (a lane change was needed)."""
    return abs(rec.start_y - rec.target_y) > 0.5


def overshoot_of(y: np.ndarray, start_y: float, target_y: float) -> float:
    """Largest excursion of the lateral positions ``y`` beyond ``target_y`` in the direction
    from ``start_y`` [m]; NaN when the start is in the target lane (no change to overshoot)."""
    if abs(start_y - target_y) <= 0.5:
        return math.nan
    direction = math.copysign(1.0, target_y - start_y)
    return max(0.0, float(np.max(direction * (np.asarray(y) - target_y))))


def overshoot(rec: EpisodeRecord) -> float:
    """Largest excursion beyond the target lane's centre in the direction of the change [m]."""
    return overshoot_of(rec.trace["y"], rec.start_y, rec.target_y)


def episode_metrics(rec: EpisodeRecord) -> dict[str, float | int | bool]:
    """Metrics of one episode (RMS errors named ``<quantity>_rms``)."""
    out: dict[str, float | int | bool] = {
        "seed": rec.seed,
        "steps": rec.steps,
        "return": rec.episode_return,
        "lane_change": changes_lane(rec),
        "collided": rec.collided,
        "reached_target": rec.reached_target,
        "success": rec.reached_target and not rec.collided,
        "overshoot": overshoot(rec),
        "final_offset": float(rec.trace["y"][-1] - rec.target_y),
    }
    out.update({f"{k}_rms": _rms(v) for k, v in _sq_errors(rec).items()})
    return out


def summarize(records: Sequence[EpisodeRecord]) -> dict[str, float | int]:
    """Aggregate over episodes; RMS errors pool every sample of every episode."""
    per = [episode_metrics(r) for r in records]
    changes = [m for m in per if m["lane_change"]]
    shoots = np.array([m["overshoot"] for m in changes], dtype=np.float64)
    out: dict[str, float | int] = {
        "episodes": len(per),
        "lane_change_episodes": len(changes),
        "collisions": sum(bool(m["collided"]) for m in per),
        "success_rate": float(np.mean([m["success"] for m in per])) if per else math.nan,
        "lane_change_success_rate": (float(np.mean([m["success"] for m in changes]))
                                     if changes else math.nan),
        "overshoot_mean": float(shoots.mean()) if shoots.size else math.nan,
        "overshoot_max": float(shoots.max()) if shoots.size else math.nan,
        "final_offset_abs_mean": float(np.mean([abs(float(m["final_offset"])) for m in per])),
    }
    pooled: dict[str, list[np.ndarray]] = {}
    for rec in records:
        for key, sq in _sq_errors(rec).items():
            pooled.setdefault(key, []).append(sq)
    out.update({f"{k}_rms": _rms(np.concatenate(v)) for k, v in pooled.items()})
    return out
