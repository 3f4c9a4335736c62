"""A recording over several sittings: what a dataset folder says about the episodes still to drive.

A recording stopped early (Esc, Ctrl-C, SIGTERM) saves the episodes kept so far with its plan
in the metadata (``sittings``: episodes planned, the next episode index, seed, keep rule, ...).
When no episode was kept yet, the folder holds only ``progress.json`` with the same plan.
``python -m memrl.record resume=<folder>`` reads the plan back (:func:`read_plan`), drives
episodes ``next_episode ..`` with the same scene seeds (episode ``i``: ``seed + i``), and saves
the old and the new transitions together.
"""

from __future__ import annotations

import json
import logging
import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from memrl.data.demos import METADATA_FILE, DemoDatasetError, load_demos, read_metadata
from memrl.errors import UserError

log = logging.getLogger(__name__)

PROGRESS_FILE = "progress.json"
"""The plan of a recording that kept no episode yet (a folder without a dataset)."""


@dataclass
class Plan:
    """The episodes a recording drives, kept in its folder between sittings."""

    episodes: int
    """Episodes planned in all sittings."""
    seed: int
    keep: str
    tail_steps: int | None
    action_noise: float
    source: str
    person: str | None = None
    next_episode: int = 0
    """Episodes finished in earlier sittings (the next one to drive)."""
    env_config: dict[str, Any] = field(default_factory=dict)
    recorded: list[dict[str, Any]] = field(default_factory=list)
    """Every finished episode of earlier sittings (``EpisodeStats`` fields), kept or not."""
    kept: list[int] = field(default_factory=list)
    """Indices into ``recorded`` of the kept ones."""

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def read_plan(folder: Path) -> tuple[Plan, Any]:
    """The plan of a stopped recording and its saved transitions (None when none were kept).

    Raises:
        UserError: naming the folder, when it holds no resumable recording or is finished.
    """
    if not folder.is_dir():
        raise UserError(f"resume: no folder {folder} (give the folder a stopped recording printed)")
    progress = folder / PROGRESS_FILE
    try:
        if (folder / METADATA_FILE).is_file():
            meta = read_metadata(folder)
            if "sittings" not in meta:
                raise UserError(f"resume: {folder / METADATA_FILE} has no 'sittings' plan (a dataset "
                                "recorded before resume existed, or an example); record a new one")
            plan, td = Plan(**meta["sittings"]), load_demos(folder)
        elif progress.is_file():
            plan, td = Plan(**json.loads(progress.read_text())), None
        else:
            raise UserError(f"resume: {folder} holds no recording ({METADATA_FILE} or {PROGRESS_FILE})")
    except (ValueError, TypeError) as err:
        bad = progress if progress.is_file() else folder / METADATA_FILE
        raise UserError(f"resume: {bad}: unreadable plan ({err})") from None
    except DemoDatasetError as err:
        raise UserError(f"resume: {err}") from None
    if plan.next_episode >= plan.episodes:
        raise UserError(f"resume: {folder} is finished ({plan.next_episode} of {plan.episodes} episodes "
                        "driven); raise episodes= to drive more")
    return plan, td


def write_progress(folder: Path, plan: Plan) -> None:
    """A folder that holds only the plan (no episode kept yet)."""
    folder.mkdir(parents=True, exist_ok=True)
    tmp = folder / (PROGRESS_FILE + ".tmp")
    tmp.write_text(json.dumps(plan.to_json(), indent=2))
    tmp.replace(folder / PROGRESS_FILE)


def clean_stale(path: Path) -> list[Path]:
    """Remove what an interrupted save to ``path`` left beside it (``.<name>.tmp-*``,
    ``.<name>.old-*``); returns what was removed."""
    gone = []
    if path.parent.is_dir():
        for stale in [*path.parent.glob(f".{path.name}.tmp-*"), *path.parent.glob(f".{path.name}.old-*")]:
            shutil.rmtree(stale, ignore_errors=True)
            log.info("removed %s, left by an interrupted save", stale)
            gone.append(stale)
    return gone
