"""Graceful stop on SIGINT (Ctrl-C) and SIGTERM.

:func:`install` (called by :func:`memrl.cli.run_hydra`) replaces Python's handlers: a signal
raises :class:`Interrupted` at once, except inside :func:`deferred` (the training loop), where it
only sets a flag that the loop checks once per iteration (:func:`stop_requested`): the loop
then writes its checkpoint and raises :class:`Interrupted` itself. A second signal while a stop
is pending raises at once. The command line turns :class:`Interrupted` into one line with the
resume command and exit status 128 + signal number (130 for SIGINT, 143 for SIGTERM).
"""

from __future__ import annotations

import os
import signal
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

SIGNALS = (signal.SIGINT, signal.SIGTERM)

_state: dict[str, Any] = {"defer": 0, "pending": None}


class Interrupted(BaseException):
    """A stop asked for by a signal (a BaseException, like KeyboardInterrupt: ``except
    Exception`` clean-up code does not swallow it)."""

    def __init__(self, signum: int) -> None:
        self.signum = int(signum)
        super().__init__(f"stopped by {signal.Signals(self.signum).name}")

    @property
    def exit_status(self) -> int:
        """128 + the signal number, as a shell reports a process ended by it."""
        return 128 + self.signum

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name


def _handler(signum: int, frame: Any) -> None:
    if _state["defer"] > 0 and _state["pending"] is None:
        _state["pending"] = signum
        return
    if _state.get("quiet"):  # a pool worker outside a training loop: end without a traceback
        os._exit(128 + signum)
    raise Interrupted(signum)


def install(worker: bool = False) -> None:
    """Handle SIGINT and SIGTERM as above (main thread only; a no-op elsewhere). In a pool
    worker (``worker=True``) a signal outside :func:`deferred` ends the process at once and
    quietly: the parent stops the pool, and a training run resumes from its last checkpoint."""
    _state["quiet"] = worker
    try:
        for sig in SIGNALS:
            signal.signal(sig, _handler)
    except ValueError:  # not the main thread
        pass


def uninstall() -> None:
    """Back to the default handlers (KeyboardInterrupt for SIGINT; SIGTERM kills)."""
    try:
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
    except ValueError:
        pass


@contextmanager
def deferred() -> Iterator[None]:
    """Within this block a signal only asks for a stop (:func:`stop_requested`). A stop asked
    for but not acted on (the work ended first) is raised on leaving the block, so that the
    process still stops."""
    _state["defer"] += 1
    try:
        yield
    finally:
        _state["defer"] -= 1
    if _state["defer"] == 0 and _state["pending"] is not None:
        stop()


def stop_requested() -> int | None:
    """The signal that asked for a stop, if any (checked once per loop iteration)."""
    return _state["pending"]


def interruption(err: BaseException) -> Interrupted | None:
    """The :class:`Interrupted` that ``err`` was raised while handling, if any. Library clean-up
    code that fails while the signal's exception passes through it replaces that exception with
    its own (tensordict's ``to_module`` context raises ``RuntimeError: Converting a tensordict
    to boolean value``), which would read as a failed run instead of a stop."""
    seen: set[int] = set()
    link: BaseException | None = err
    while link is not None and id(link) not in seen:
        if isinstance(link, Interrupted):
            return link
        seen.add(id(link))
        link = link.__cause__ or link.__context__
    return None


def stop() -> None:
    """Raise :class:`Interrupted` for the pending signal (after the caller's checkpoint)."""
    signum = _state["pending"]
    _state["pending"] = None
    raise Interrupted(signum)
