"""Ending a command early on request: Esc in the driving window, Ctrl-C (SIGINT), SIGTERM.

One exception per way of ending, one set of exit statuses:

* :class:`Interrupted` is a signal (a BaseException, like KeyboardInterrupt: ``except
  Exception`` clean-up code does not swallow it). :func:`memrl.cli.run_task` turns it into one
  line with the command that continues the work and exit status 128 + signal number
  (:data:`SIGINT_EXIT` 130, :data:`SIGTERM_EXIT` 143, as a shell reports a command killed by
  those signals).
* :class:`Stopped` is raised by a task that ended early on purpose and wrote what it had (an
  evaluation, a recording): :func:`memrl.cli.run_task` prints its one line and exits with its
  status.

Two ways to have signals raise :class:`Interrupted`:

* :func:`install` (called by :func:`memrl.cli.run_hydra`) replaces Python's handlers for the
  whole process. Inside :func:`deferred` (the training loop) a signal only sets a flag that the
  loop checks once per iteration (:func:`stop_requested`): the loop then writes its checkpoint
  and raises it (:func:`raise_pending`). A second signal while a stop is pending raises at once.
* :class:`SignalGuard` does the same for one block (and restores the handlers before it), also
  for a Python caller that never called :func:`install`; inside :meth:`SignalGuard.deferred`
  a signal is only noted (``pending``) and acts when the caller checks (a dataset being saved
  is not cut in half).
"""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType, TracebackType
from typing import Any

SIGINT_EXIT = 130
SIGTERM_EXIT = 143
EXIT_OF = {signal.SIGINT: SIGINT_EXIT, signal.SIGTERM: SIGTERM_EXIT}
"""Exit status of each handled signal."""
SIGNALS = tuple(EXIT_OF)


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


class Stopped(Exception):  # noqa: N818 - an outcome, not an error
    """A task ended early on request; ``str()`` is its one line, ``status`` the exit status."""

    def __init__(self, message: str, status: int = SIGINT_EXIT) -> None:
        super().__init__(message)
        self.status = status

    @classmethod
    def by(cls, message: str, stop: Interrupted | None) -> Stopped:
        """Ended by the signal ``stop`` (its exit status), or by Esc (None: 130, as Ctrl-C)."""
        return cls(message, SIGINT_EXIT if stop is None else stop.exit_status)


def interrupted_by(err: KeyboardInterrupt | Interrupted) -> Interrupted:
    """The signal stop ``err`` is: itself, or SIGINT for a ``KeyboardInterrupt`` (Python's own
    handler, where none of these is installed)."""
    return err if isinstance(err, Interrupted) else Interrupted(signal.SIGINT)


def how_stopped(stop: Interrupted | None) -> str:
    """The words of a stopped task's line: ``interrupted (SIGINT)``, ``interrupted (SIGTERM)``;
    ``stopped`` without a signal (Esc)."""
    return "stopped" if stop is None else f"interrupted ({stop.name})"


# ------------------------------------------------------------------ process-wide handlers
_state: dict[str, Any] = {"defer": 0, "pending": None}


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
        raise_pending()


def stop_requested() -> int | None:
    """The signal that asked for a stop, if any (checked once per loop iteration)."""
    return _state["pending"]


def request_stop(signum: int) -> None:
    """Ask for a stop as the signal ``signum`` would inside :func:`deferred` (the other runs of a
    group stop at their next checkpoint after one of them raised the stop)."""
    _state["pending"] = int(signum)


def raise_pending() -> None:
    """Raise :class:`Interrupted` for the pending signal (after the caller's checkpoint)."""
    signum = _state["pending"]
    _state["pending"] = None
    raise Interrupted(signum)


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


# ------------------------------------------------------------------ handlers for one block
class SignalGuard:
    """Within the block, SIGINT and SIGTERM raise :class:`Interrupted`; inside
    :meth:`deferred`, both are only noted (``pending``) and act when the caller checks.
    Outside the main thread it does nothing (signals only reach the main thread)."""

    def __init__(self) -> None:
        self.pending: int | None = None
        self._deferring = False
        self._old: dict[int, Any] = {}

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self._deferring:
            self.pending = self.pending or signum
            return
        raise Interrupted(signum)

    def __enter__(self) -> SignalGuard:
        if threading.current_thread() is threading.main_thread():
            for sig in SIGNALS:
                self._old[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, kind: type[BaseException] | None, err: BaseException | None,
                 tb: TracebackType | None) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)

    def deferred(self) -> _Deferred:
        """A block in which signals wait (``with guard.deferred(): save(...)``)."""
        return _Deferred(self)


class _Deferred:
    def __init__(self, guard: SignalGuard) -> None:
        self.guard = guard

    def __enter__(self) -> None:
        self.guard._deferring = True

    def __exit__(self, *exc: object) -> None:
        self.guard._deferring = False


# ------------------------------------------------------------------ the command that goes on
OUTPUT_KEYS = ("hydra.run.dir", "hydra.output_subdir", "paths.output_root")
"""Overrides of where a command's folder goes, kept in a printed re-run command (else the
re-run's log and ``.hydra/`` land in another folder)."""


def output_overrides() -> list[str]:
    """This Hydra run's overrides of :data:`OUTPUT_KEYS`, unquoted (none outside a Hydra run)."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return []
    given = HydraConfig.get().overrides  # Hydra keeps its own keys' overrides apart from the task's
    every = [str(o) for o in [*given.hydra, *given.task]]
    return [o for o in every if o.split("=", 1)[0].lstrip("+") in OUTPUT_KEYS]
