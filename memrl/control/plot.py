"""PNG of one deploy episode: trajectory, commands, tracked and estimated values, actuators."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from memrl.control.episode import EpisodeRecord


def plot_episode(rec: EpisodeRecord, lanes_count: int, lane_width: float, path: Path,
                 title: str = "") -> Path:
    """Draw ``rec`` into a PNG at ``path`` (Agg canvas, no pyplot state) and return the path.

    Panels: top view of the road with the true, estimated and GNSS positions; speed and
    curvature (command, truth, estimate, raw sensor); accelerator force and steering.
    """
    t = rec.trace
    fig = Figure(figsize=(11, 12), layout="constrained")
    FigureCanvasAgg(fig)
    ax_xy, ax_y, ax_v, ax_k, ax_u = fig.subplots(5, 1, height_ratios=[1.3, 1, 1, 1, 1])

    # top view: road edges, lane markings, target centre line
    edges = (-0.5 * lane_width, (lanes_count - 0.5) * lane_width)
    for y in edges:
        ax_xy.axhline(y, color="k", lw=1.5)
    for i in range(1, lanes_count):
        ax_xy.axhline((i - 0.5) * lane_width, color="0.6", ls="--", lw=1)
    ax_xy.axhline(rec.target_y, color="tab:green", lw=1, alpha=0.6, label="target lane centre")
    g = t["gnss"]
    ax_xy.plot(g[:, 1], g[:, 2], ".", color="0.5", ms=3, label="GNSS fixes")
    ax_xy.plot(t["x"], t["y"], color="k", lw=1.5, label="true")
    ax_xy.plot(t["est_x"], t["est_y"], color="tab:orange", lw=1, label="EKF estimate")
    ax_xy.set(xlabel="x along the road [m]", ylabel="y [m]", ylim=(edges[1] + 1, edges[0] - 1))
    ax_xy.legend(loc="upper right", fontsize=8, ncol=4)
    ax_xy.set_title(title or f"deploy episode seed {rec.seed}: "
                    f"{'collision' if rec.collided else 'no collision'}, "
                    f"{'reached' if rec.reached_target else 'missed'} target lane")

    time = t["time"]
    ax_y.axhline(rec.target_y, color="tab:green", lw=1, alpha=0.6, label="target lane centre")
    ax_y.plot(time, t["y"], color="k", label="true")
    ax_y.plot(time, t["est_y"], color="tab:orange", lw=1, label="estimate")
    ax_y.plot(g[:, 0], g[:, 2], ".", color="0.5", ms=3, label="GNSS")
    ax_y.set(ylabel="lateral position y [m]", ylim=(edges[1] + 0.5, edges[0] - 0.5))
    ax_y.legend(loc="upper right", fontsize=8, ncol=4)

    for ax, key, unit in ((ax_v, "speed", "m/s"), (ax_k, "curvature", "rad/m")):
        ax.plot(time, t[f"raw_{key}"], color="0.8", lw=0.5, label="raw sensor")
        ax.plot(time, t[f"cmd_{key}"], color="tab:blue", lw=1.5, drawstyle="steps-post",
                label="command (set point)")
        ax.plot(time, t[key], color="k", lw=1, label="true")
        ax.plot(time, t[f"est_{key}"], color="tab:orange", lw=1, label="estimate")
        ax.set(ylabel=f"{key} [{unit}]")
        ax.legend(loc="upper right", fontsize=8, ncol=4)
    lo, hi = np.percentile(np.concatenate([t["cmd_curvature"], t["curvature"]]), [0, 100])
    pad = max(0.2 * (hi - lo), 0.005)
    ax_k.set_ylim(lo - pad, hi + pad)

    ax_u.plot(time, t["force_demand"] / 1000, color="tab:blue", lw=0.8, label="force demand [kN]")
    ax_u.plot(time, t["force"] / 1000, color="k", lw=1, label="force delivered [kN]")
    ax_u.set(xlabel="time [s]", ylabel="accelerator [kN]")
    ax_s = ax_u.twinx()
    ax_s.plot(time, np.degrees(t["steer"]), color="tab:red", lw=1, label="road-wheel angle [deg]")
    ax_s.set_ylabel("steering [deg]", color="tab:red")
    ax_u.legend(loc="upper left", fontsize=8)
    ax_s.legend(loc="upper right", fontsize=8)

    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    return path
