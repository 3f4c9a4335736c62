"""Run records: the per-episode CSV, the per-update-interval CSV and the TorchRL logger."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path
from typing import Any

EPISODE_FIELDS = ("episode", "env_steps", "return", "survival_steps", "length", "collided",
                  "reached_target", "epsilon", "stage")
"""Columns of ``episodes.csv``: ``env_steps`` is the total env steps at the episode's end;
``survival_steps`` the steps until a collision (the episode length when none, as Fig. 5)."""

UPDATE_FIELDS = ("updates", "env_steps", "stage", "loss", "mean_q", "demo_share",
                 "demo_count_min", "demo_count_max", "updates_per_s", "frames_per_s", "epsilon")
"""Columns of ``updates.csv``, one row per ``log_every`` updates: means over the interval, and
the min/max demo count of the interval's batches (equal in stratified mode A)."""


class CsvTable:
    """An append-only CSV with a header; on resume it is cut back to the checkpoint's rows."""

    def __init__(self, path: Path, fields: Sequence[str]) -> None:
        self.path, self.fields = path, tuple(fields)
        if not path.exists():
            path.parent.mkdir(parents=True, exist_ok=True)
            with path.open("w", newline="") as f:
                csv.writer(f).writerow(self.fields)

    def append(self, row: dict[str, Any]) -> None:
        with self.path.open("a", newline="") as f:
            csv.DictWriter(f, self.fields).writerow(row)

    def rows(self) -> list[dict[str, str]]:
        with self.path.open(newline="") as f:
            return list(csv.DictReader(f))

    def truncate(self, keep: int) -> None:
        """Keep the header and the first ``keep`` rows (work after a checkpoint is redone)."""
        rows = self.rows()[:keep]
        with self.path.open("w", newline="") as f:
            writer = csv.DictWriter(f, self.fields)
            writer.writeheader()
            writer.writerows(rows)


class RunRecords:
    """Everything a run writes besides checkpoints."""

    def __init__(self, out_dir: Path, logger: Any | None) -> None:
        self.episodes = CsvTable(out_dir / "episodes.csv", EPISODE_FIELDS)
        self.updates = CsvTable(out_dir / "updates.csv", UPDATE_FIELDS)
        self.logger = logger

    def episode(self, row: dict[str, Any]) -> None:
        self.episodes.append(row)
        if self.logger is not None:
            for key in ("return", "survival_steps", "reached_target", "collided"):
                self.logger.log_scalar(f"episode/{key}", float(row[key]), step=int(row["env_steps"]))

    def update(self, row: dict[str, Any]) -> None:
        self.updates.append(row)
        if self.logger is not None:
            for key in ("loss", "mean_q", "demo_share", "updates_per_s", "frames_per_s"):
                if row.get(key) not in (None, ""):
                    self.logger.log_scalar(f"train/{key}", float(row[key]), step=int(row["updates"]))

    def rewind(self, episodes: int, update_rows: int) -> None:
        self.episodes.truncate(episodes)
        self.updates.truncate(update_rows)
