"""Worker processes that end with the process that started them.

``ProcessPoolExecutor`` workers outlive a parent killed with SIGTERM or SIGKILL: they finish
the task they hold (a whole training run of a study) and only then notice. A study stopped
with ``kill <pid>`` kept training in the background, holding the run's lock, so that the next
call of the same command found the run busy. Hand-written because neither
``concurrent.futures`` nor ``multiprocessing`` offers it: Linux's ``PR_SET_PDEATHSIG``.
"""

from __future__ import annotations

import os
import signal
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from memrl.stop import Interrupted, install

PR_SET_PDEATHSIG = 1
"""``prctl`` option: the signal this process gets when its parent ends (linux/prctl.h)."""


def die_with_parent() -> None:
    """Pool initializer: SIGTERM this worker when its parent ends (Linux; elsewhere nothing).
    A run it was training stays resumable from its last checkpoint."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes
    import multiprocessing

    known = multiprocessing.parent_process()  # the pool's process, even if it has ended already
    parent = known.pid if known is not None else os.getppid()
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
    except (OSError, AttributeError):  # no prctl (another libc): keep the old behaviour
        return
    if os.getppid() != parent:  # the parent ended before prctl took effect
        os.kill(os.getpid(), signal.SIGTERM)


def worker_start() -> None:
    """Pool initializer of every memrl pool: :func:`die_with_parent`, and SIGINT / SIGTERM
    handled as in the main process (:func:`memrl.stop.install`): a training worker stops at its
    next checkpoint, any other ends at once."""
    die_with_parent()
    install(worker=True)


@contextmanager
def stopped_with_parent(pool: Any) -> Iterator[None]:
    """On a stop in the parent (:class:`~memrl.stop.Interrupted`, or ``KeyboardInterrupt``
    where no handler of :mod:`memrl.stop` is installed):
    cancel the jobs not started, send SIGTERM to the workers (a training run writes its
    checkpoint and stops), wait for them (no orphans, no leaked semaphores), then re-raise.
    Without this, Ctrl-C in a multi-worker evaluation left the workers to drive every queued
    episode before the command ended."""
    try:
        yield
    except (Interrupted, KeyboardInterrupt):
        processes = list((getattr(pool, "_processes", None) or {}).values())
        pool.shutdown(wait=False, cancel_futures=True)
        for proc in processes:
            if proc.is_alive():
                proc.terminate()
        for proc in processes:
            proc.join(timeout=300)
        pool.shutdown(wait=True)
        raise
