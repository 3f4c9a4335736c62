"""The study's record, ``study.json``: read whole, changed under a lock, replaced atomically.

Several ``memrl.study`` calls may share one study folder (one process per mode or seed list):
each reads the record, checks its overrides against it and writes it back. filelock serialises
that read-modify-write (a second call waits a moment), and ``os.replace`` means a reader never
sees a half-written file.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from filelock import FileLock

from memrl.errors import UserError

STUDY_JSON = "study.json"
"""The study's own record: the grid and the train overrides it was made with."""


def read_record(file: Path) -> dict[str, Any]:
    """The record's values ({} when there is none); a damaged file is refused in one line."""
    if not file.is_file():
        return {}
    try:
        doc = json.loads(file.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise UserError(f"{file}: unreadable ({err}); restore it, or remove it to record this "
                        "call's train overrides and variants as the study's") from None
    if not isinstance(doc, dict):
        raise UserError(f"{file}: not a study record (a JSON object), got {type(doc).__name__}")
    return doc


def write_record(file: Path, doc: dict[str, Any]) -> None:
    """Replace the record at once (a temporary file beside it, then ``os.replace``)."""
    tmp = file.with_name(f".{file.name}.tmp-{os.getpid()}")
    tmp.write_text(json.dumps(doc, indent=2))
    os.replace(tmp, file)


@contextmanager
def record_lock(folder: Path) -> Iterator[Path]:
    """Hold the study folder's record lock (made with the folder); yields the record's path."""
    folder.mkdir(parents=True, exist_ok=True)
    with FileLock(folder / f".{STUDY_JSON}.lock"):  # filelock: an OS lock, gone with its process
        yield folder / STUDY_JSON
