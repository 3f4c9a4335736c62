"""Run records: the per-episode CSV, the per-update-interval CSV and the TorchRL logger."""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from memrl.csv_table import CsvTable  # noqa: F401 (re-export)
from memrl.loggers import HeldLog

log = logging.getLogger(__name__)

EPISODE_FIELDS = ("episode", "env_steps", "return", "survival_steps", "length", "collided",
                  "reached_target", "epsilon", "stage")
"""Columns of ``episodes.csv``: ``env_steps`` is the total env steps at the episode's end;
``survival_steps`` the steps until a collision (the episode length when none, as Fig. 5)."""

UPDATE_FIELDS = ("updates", "env_steps", "stage", "loss", "mean_q", "demo_share",
                 "demo_count_min", "demo_count_max", "updates_per_s", "frames_per_s", "epsilon")
"""Columns of ``updates.csv``, one row per ``log_every`` updates: means over the interval, and
the min/max demo count of the interval's batches (equal in stratified mode A)."""


EPISODE_METRICS = ("return", "survival_steps", "reached_target", "collided", "epsilon")
"""Logger points of each episode: ``episode/<key>`` at the episode's env steps."""

UPDATE_METRICS = ("loss", "mean_q", "demo_share", "updates", "updates_per_s", "frames_per_s",
                  "epsilon")
"""Logger points of each updates.csv row: ``train/<key>`` at its env steps; in mode B's stage 1
(no env steps) ``stage1/<key>`` at its updates."""


class RunRecords:
    """Everything a run writes besides checkpoints.

    Args:
        out_dir: the run folder.
        logger: a TorchRL logger or None; its points are held until the next checkpoint
            (:class:`memrl.loggers.HeldLog`), so a resumed run logs nothing twice.
        echo: also log each updates.csv row as a line (runs without a progress bar).
    """

    def __init__(self, out_dir: Path, logger: Any | None, echo: bool = False) -> None:
        self.episodes = CsvTable(out_dir / "episodes.csv", EPISODE_FIELDS)
        self.updates = CsvTable(out_dir / "updates.csv", UPDATE_FIELDS)
        self.log = HeldLog(logger) if logger is not None else None
        self.echo = echo

    def _points(self, prefix: str, values: Mapping[str, Any], keys: Iterable[str], step: int) -> None:
        if self.log is not None:
            for key in keys:
                if values.get(key) not in (None, ""):
                    self.log.log_scalar(f"{prefix}/{key}", float(values[key]), step)

    def episode(self, row: dict[str, Any]) -> None:
        self.episodes.append(row)
        self._points("episode", row, EPISODE_METRICS, int(row["env_steps"]))

    def update(self, row: dict[str, Any], offline: bool = False) -> None:
        """A row of ``updates.csv``; its logger points go under ``stage1/`` at its updates for
        an offline stage (no env steps), else under ``train/`` at its env steps."""
        self.updates.append(row)
        if offline:
            self._points("stage1", row, UPDATE_METRICS, int(row["updates"]))
        else:
            self._points("train", row, UPDATE_METRICS, int(row["env_steps"]))
        if self.echo:
            log.info("updates %d, env steps %d, stage %s: loss %.4g, mean Q %.4g, eps %.3f, "
                     "%.1f updates/s, %.0f env steps/s", row["updates"], row["env_steps"],
                     row["stage"], row["loss"], row["mean_q"], row["epsilon"],
                     row["updates_per_s"], row["frames_per_s"])

    def stage1_check(self, updates: int, values: Mapping[str, float]) -> None:
        """Mode B stage 1's check (loss, agreement and its parts, drives) at ``updates``."""
        self._points("stage1", values, values, updates)

    def flush(self) -> None:
        """Hand the held logger points to the backend (after each checkpoint)."""
        if self.log is not None:
            self.log.flush()

    def rewind(self, episodes: int, update_rows: int) -> None:
        """After a resume: keep the CSV rows up to the checkpoint (the logger never got the
        later points, see :class:`memrl.loggers.HeldLog`)."""
        self.episodes.truncate(episodes)
        self.updates.truncate(update_rows)
