"""``study.status=true``: where each run of a study stands, read from its folder; nothing is
trained, evaluated or reported (Hydra records the call in
``.hydra/`` and ``study.log``, as for every call).

Per run: its state (finished, running now, resumable from a checkpoint, not started), its
stage, env steps against the budget and updates (the last ``updates.csv`` row: live for a run
that is training), where a resume would continue from (the last checkpoint's counters), and
whether its protocol evaluation exists.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from memrl.run_lock import held_elsewhere
from memrl.studies.grid import Cell


@dataclass
class RunStatus:
    """One run of the grid."""

    name: str
    state: str
    """finished | running | resumable | not started | started (a folder, no checkpoint yet)."""
    stage: str = ""
    env_steps: int | None = None
    updates: int | None = None
    checkpoint: str = ""
    """Where a resume continues from: stage, env steps and updates of ``checkpoints/last``."""
    evaluated: bool = False


def _last_row(path: Path) -> dict[str, str] | None:
    if not path.is_file():
        return None
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    return rows[-1] if rows else None


def _checkpoint(run: Path) -> str:
    """``checkpoints/last``'s counters, or '' (none, or unreadable: the resume will say why)."""
    state_file = run / "checkpoints" / "last" / "state.pt"
    if not state_file.is_file():
        return ""
    import torch

    try:
        c = torch.load(state_file, weights_only=False, map_location="cpu")["counters"]
    except Exception:  # noqa: BLE001 - a damaged checkpoint: the resume itself names the file
        return "unreadable"
    return f"{c['stage']}: {int(c['frames']):,} env steps, {int(c['updates']):,} updates"


def run_status(cell: Cell) -> RunStatus:
    """Where ``cell``'s run stands."""
    run = cell.run_dir
    evaluated = (run / "eval" / "eval.json").is_file()
    if cell.finished():
        summary: dict[str, Any] = json.loads((run / "summary.json").read_text())
        return RunStatus(cell.name, "finished", str(summary.get("stage", "")), summary.get("frames"),
                         summary.get("updates"), "", evaluated)
    if not run.is_dir():
        return RunStatus(cell.name, "not started")
    row = _last_row(run / "updates.csv")
    checkpoint = _checkpoint(run)
    state = "running" if held_elsewhere(run) else "resumable" if cell.resumable() else "started"
    return RunStatus(cell.name, state, row["stage"] if row else "",
                     int(row["env_steps"]) if row else None, int(row["updates"]) if row else None,
                     checkpoint, evaluated)


def budget(cell: Cell) -> str:
    """The run's budget: ``100,000 env steps`` / ``300 episodes``."""
    assert cell.cfg is not None
    parts = [f"{int(cell.cfg.total_frames):,} env steps" if cell.cfg.total_frames is not None else "",
             f"{int(cell.cfg.total_episodes):,} episodes" if cell.cfg.total_episodes is not None else ""]
    return " or ".join(p for p in parts if p)


def status_table(cells: list[Cell]) -> list[str]:
    """The lines ``study.status=true`` prints: a count per state, then a row per run."""
    found = [run_status(c) for c in cells]
    counts = {s: sum(r.state == s for r in found)
              for s in ("finished", "running", "resumable", "started", "not started")}
    lines = [", ".join(f"{n} {s}" for s, n in counts.items() if n) + f" of {len(found)} runs; "
             f"{sum(r.evaluated for r in found)} evaluated", "",
             "| run | state | stage | env steps | updates | budget | resumes from | evaluated |",
             "|---|---|---|---|---|---|---|---|"]
    for cell, r in zip(cells, found, strict=True):
        steps = "" if r.env_steps is None else f"{r.env_steps:,}"
        updates = "" if r.updates is None else f"{r.updates:,}"
        lines.append(f"| {r.name} | {r.state} | {r.stage} | {steps} | {updates} | {budget(cell)} | "
                     f"{r.checkpoint} | {'yes' if r.evaluated else 'no'} |")
    return lines
