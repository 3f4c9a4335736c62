"""Ending a command early on request: Esc in the driving window, Ctrl-C (SIGINT), SIGTERM.

:class:`Stopped` is raised by a task that ended early on purpose; :func:`memrl.cli.run_task`
prints its one line and exits with its status (130 for SIGINT and Esc, 143 for SIGTERM, as a
shell reports a command killed by those signals). :class:`SignalGuard` turns SIGTERM into
:class:`Terminated` like Python turns SIGINT into ``KeyboardInterrupt``, and can defer both
while something must not be cut in half (a dataset being saved).
"""

from __future__ import annotations

import signal
import threading
from types import FrameType, TracebackType
from typing import Any

SIGINT_EXIT = 130
SIGTERM_EXIT = 143
EXIT_OF = {signal.SIGINT: SIGINT_EXIT, signal.SIGTERM: SIGTERM_EXIT}


class Stopped(Exception):  # noqa: N818 - an outcome, not an error
    """A task ended early on request; ``str()`` is its one line, ``status`` the exit status."""

    def __init__(self, message: str, status: int = SIGINT_EXIT) -> None:
        super().__init__(message)
        self.status = status


class Terminated(BaseException):  # noqa: N818 - like KeyboardInterrupt
    """SIGTERM arrived (raised where the program was, as SIGINT raises KeyboardInterrupt)."""


def exit_status_of(err: BaseException) -> int:
    """130 for KeyboardInterrupt, 143 for :class:`Terminated`."""
    return SIGTERM_EXIT if isinstance(err, Terminated) else SIGINT_EXIT


class SignalGuard:
    """Within the block, SIGTERM raises :class:`Terminated` and SIGINT ``KeyboardInterrupt``;
    inside :meth:`deferred`, both are only noted (``pending``) and act when the caller checks.
    Outside the main thread it does nothing (signals only reach the main thread)."""

    def __init__(self) -> None:
        self.pending: int | None = None
        self._deferring = False
        self._old: dict[int, Any] = {}

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self._deferring:
            self.pending = self.pending or signum
            return
        raise Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()

    def __enter__(self) -> SignalGuard:
        if threading.current_thread() is threading.main_thread():
            for sig in EXIT_OF:
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
