"""Whether a window can open: the recorder refuses at start, in one line, instead of hanging."""

from __future__ import annotations

import os
import sys

from memrl.errors import UserError

WINDOW_CLASS = "memrl"
"""X window class (and instance name) of the recorder's window: ``xdotool search --classname memrl``."""
HEADLESS_DRIVERS = ("dummy", "offscreen")
"""SDL video drivers that need no display (tests; nothing can be seen)."""
HOW = "run it on a desktop, set DISPLAY to a running X server, or wrap the command in xvfb-run"


class NoDisplayError(UserError, RuntimeError):
    """No display for the recorder's window."""


def require_display() -> None:
    """Raise :class:`NoDisplayError` unless a window can be opened (X11/Wayland on Linux)."""
    driver = os.environ.get("SDL_VIDEODRIVER", "")
    if driver in HEADLESS_DRIVERS or not sys.platform.startswith("linux"):
        return
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise NoDisplayError(f"no display for the driving window (DISPLAY is not set): {HOW}")
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    import pygame

    try:
        pygame.display.init()
    except pygame.error as err:
        where = os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
        raise NoDisplayError(f"cannot open the driving window on display {where!r} ({err}): {HOW}") from err
    finally:
        pygame.display.quit()
