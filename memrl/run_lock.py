"""One process at a time per run folder: a training run, or its resumption, holds a file lock."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from filelock import FileLock, Timeout

from memrl.errors import UserError

LOCK_NAME = "train.lock"
"""Lock file in the run folder (an OS lock: released when the process ends, however it ends)."""


class RunFolderBusy(UserError, RuntimeError):
    """Another process is training in (or resuming) the same run folder."""


@contextmanager
def run_lock(run_dir: Path) -> Iterator[None]:
    """Hold the run folder's lock for the block; refuse at once if another process holds it."""
    lock = FileLock(run_dir / LOCK_NAME, timeout=0)
    try:
        lock.acquire()
    except Timeout:
        raise RunFolderBusy(f"run folder {run_dir} is in use by another process (lock "
                            f"{run_dir / LOCK_NAME}); wait for it to end or stop it, then "
                            "resume") from None
    try:
        yield
    finally:
        lock.release()


def held_elsewhere(run_dir: Path) -> bool:
    """Another process holds the run folder's lock (training or resuming it). A free lock is
    taken and released at once (a start in that instant is refused; the next call resumes)."""
    if not (run_dir / LOCK_NAME).is_file():
        return False
    lock = FileLock(run_dir / LOCK_NAME, timeout=0)
    try:
        lock.acquire()
    except Timeout:
        return True
    lock.release()
    return False
