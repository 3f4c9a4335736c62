"""``study.extend_from``: continue the finished runs of an earlier study to this study's bigger
budget, e.g. Table III at 100,000 env steps taken on to 300,000 without retraining the first
100,000.

Each cell of this grid that has no folder yet gets a copy of the earlier study's finished run of
the same name, without what marks it finished (``summary.json``, ``checkpoints/final.pt``, its
protocol evaluation ``eval/``); the grid then resumes it from its last checkpoint like a killed
run. The budget keys (``total_frames``, ``total_episodes``) may differ from the earlier run's,
every other key must match (the resume's own check, made before anything is copied). A run
continued this way ends where an uninterrupted run at the bigger budget ends (tested):
epsilon's decay is set in env steps (``agent.eps_decay_frames``), not as a share of the budget.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from collections.abc import Sequence
from pathlib import Path

from memrl.errors import config_error
from memrl.studies.grid import Cell
from memrl.studies.record import read_record, record_lock, write_record

log = logging.getLogger(__name__)

FINISHED_MARKS = ("summary.json", "final.pt", "eval", "train.lock")
"""What a copied run leaves behind: the marks of a finished run and its lock."""


def copy_run(src: Path, dst: Path) -> None:
    """``src`` (a run folder) to ``dst`` without :data:`FINISHED_MARKS`: the files under its
    ``checkpoints/`` as hard links (a checkpoint is replaced as a new folder, never written in
    place, and a resume loads the buffer into memory), the logs and CSVs a resumed run appends
    to as copies."""

    def link_or_copy(file: str, to: str) -> None:
        if Path(file).relative_to(src).parts[0] == "checkpoints":
            try:
                os.link(file, to)
                return
            except OSError:  # another file system, or links not allowed: copy
                pass
        shutil.copy2(file, to)

    shutil.copytree(src, dst, ignore=shutil.ignore_patterns(*FINISHED_MARKS), copy_function=link_or_copy)


def sources(grid: Sequence[Cell], earlier: Path) -> list[tuple[Cell, Path]]:
    """The cells without a folder and the earlier study's finished run of each (cells it lacks
    start from scratch); refuses (one line, nothing written) an earlier run not finished, made
    under another config, or already at this budget."""
    from memrl.checkpoint import resume as ckpt
    from memrl.train import budget_reached

    if not (earlier / "runs").is_dir():
        raise config_error("study.extend_from", f"{earlier} holds no runs/ folder (give the folder of "
                           "an earlier study, its study.dir)")
    out = []
    for cell in grid:
        src = earlier / "runs" / cell.name
        if cell.run_dir.exists() or not src.exists():
            continue
        if not (src / "summary.json").is_file():
            raise config_error("study.extend_from", f"{src} has not finished (finish the earlier study "
                               "first: run its own command again)")
        assert cell.cfg is not None
        try:
            ckpt.load_state(ckpt.find(src), cell.cfg)
        except ckpt.CheckpointError as err:
            raise config_error("study.extend_from", f"{src} cannot be continued by this study: "
                               + " ".join(str(err).split())) from err
        done = json.loads((src / "summary.json").read_text())
        if budget_reached(cell.cfg, done):
            raise config_error("study.extend_from", f"{src} ended at {done['frames']:,} env steps and "
                               f"{done['episodes']:,} episodes, already within this study's budget "
                               f"(total_frames={cell.cfg.total_frames}, total_episodes="
                               f"{cell.cfg.total_episodes}): nothing to continue")
        out.append((cell, src))
    return out


def extend(pairs: Sequence[tuple[Cell, Path]], record: Path) -> list[str]:
    """Copy each earlier run (:func:`sources`) into its cell's folder and note it in the study's
    ``record`` (``study.json``: ``"extended"``, run -> the folder it continues); returns the
    cells copied, which the grid then resumes."""
    if pairs:
        with record_lock(record.parent):
            doc = read_record(record)
            doc["extended"] = {**doc.get("extended", {}), **{cell.name: str(src) for cell, src in pairs}}
            write_record(record, doc)
    for cell, src in pairs:
        tmp = cell.run_dir.with_name(cell.run_dir.name + ".extending")
        shutil.rmtree(tmp, ignore_errors=True)
        copy_run(src, tmp)
        tmp.rename(cell.run_dir)  # a kill during the copy leaves no half run folder
        log.info("%s: continued from %s", cell.name, src)
    return [cell.name for cell, _ in pairs]
