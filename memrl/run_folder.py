"""A fresh training run goes into a folder that holds no run: a folder with a run in it is
resumed (``resume=<folder>``) or, with ``overwrite=true``, replaced; never trained over.

Imports no torch (the check runs before Hydra makes the run folder).
"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from memrl.errors import UserError
from memrl.run_lock import LOCK_NAME, held_elsewhere

log = logging.getLogger(__name__)

RUN_MARKS = ("config.yaml", "checkpoints", "summary.json", "episodes.csv")
"""What a training run writes into its folder first and last: any of them marks a run."""

KEPT = (".hydra", LOCK_NAME)
"""Kept when ``overwrite=true`` replaces a run (Hydra's record of this call, the lock); and
the ``*.log`` files, which this call appends to."""


class RunFolderTaken(UserError):
    """A fresh start names a folder that holds a training run."""


def holds_run(folder: Path) -> bool:
    """Whether ``folder`` holds (part of) a training run."""
    return folder.is_dir() and any((folder / mark).exists() for mark in RUN_MARKS)


def check_new_run_folder(folder: Path, overwrite: bool) -> None:
    """Refuse a fresh start into a folder that holds a run, unless ``overwrite``."""
    if overwrite or not holds_run(folder):
        return
    marks = ", ".join(m for m in RUN_MARKS if (folder / m).exists())
    raise RunFolderTaken(f"{folder}: holds a training run already ({marks}); resume it with "
                         f"resume={folder}, pick another folder, or replace it with overwrite=true")


def check_start_folder(folder: Path, fresh: bool, overwrite: bool) -> None:
    """Before a run starts: a fresh start into a folder that holds a run is refused unless
    ``overwrite`` (a resume, or a folder another process trains in, is left to the lock)."""
    if fresh and not held_elsewhere(folder):
        check_new_run_folder(folder, overwrite)


def claim_start_folder(folder: Path, fresh: bool, overwrite: bool) -> None:
    """Under the run folder's lock: the check again (a run that ended meanwhile), and with
    ``overwrite`` the earlier run's files removed (:func:`clear_earlier_run`)."""
    if not fresh:
        return
    check_new_run_folder(folder, overwrite)
    if overwrite:
        clear_earlier_run(folder)


def planned_run_dir(cfg: Any) -> Path | None:
    """The folder Hydra makes for a composed config that holds its ``hydra`` node (the start
    checks see it): ``hydra.run.dir``, or a sweep job's ``hydra.sweep.dir/<subdir>`` once
    ``hydra.job.num`` is set; None outside Hydra (a Python caller names its own folder)."""
    if OmegaConf.select(cfg, "hydra", default=None) is None:
        return None
    if str(OmegaConf.select(cfg, "hydra.mode", default=None)).endswith("MULTIRUN"):
        sub = OmegaConf.select(cfg, "hydra.sweep.subdir", default=None,
                               throw_on_resolution_failure=False)
        return None if sub is None else Path(str(cfg.hydra.sweep.dir)) / str(sub)
    where = OmegaConf.select(cfg, "hydra.run.dir", default=None)
    return None if where is None else Path(str(where))


def clear_earlier_run(folder: Path) -> None:
    """``overwrite=true``: remove the earlier run's files (all but :data:`KEPT` and the logs)
    before the new run writes its own, so that none of them (a checkpoint, ``stage1.pt``, an
    evaluation) passes for the new run's."""
    if not holds_run(folder):
        return
    for entry in folder.iterdir():
        if entry.name in KEPT or entry.suffix == ".log":
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry)
        else:
            entry.unlink()
    log.warning("overwrite=true: the earlier run in %s was removed (its log lines are kept)", folder)
