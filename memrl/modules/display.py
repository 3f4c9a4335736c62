"""Whether a window can open: the recorder refuses at start, in one line, instead of hanging.

On Linux, SDL tries one video driver after another when X cannot be reached and may wait
there for good; so the X server named by ``DISPLAY`` is reached here first (its socket, two
seconds at most), and SDL is then told to use X11.
"""

from __future__ import annotations

import os
import re
import socket
import sys

from memrl.errors import UserError

WINDOW_CLASS = "memrl"
"""X window class (and instance name) of the recorder's window: ``xdotool search --classname memrl``."""
HEADLESS_DRIVERS = ("dummy", "offscreen")
"""SDL video drivers that need no display (tests; nothing can be seen)."""
HOW = "run it on a desktop, set DISPLAY to a running X server, or wrap the command in xvfb-run -a"


class NoDisplayError(UserError, RuntimeError):
    """No display for the recorder's window."""


def x_server_reachable(display: str, timeout: float = 2.0) -> bool:
    """Whether an X server answers at ``display`` (``[host]:N[.screen]``)."""
    m = re.fullmatch(r"(?P<host>[^:]*):(?P<n>\d+)(\.\d+)?", display)
    if m is None:
        return False
    host, n = m["host"], int(m["n"])
    try:
        if host in ("", "unix"):
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
                s.settimeout(timeout)
                for path in (f"/tmp/.X11-unix/X{n}", f"\0/tmp/.X11-unix/X{n}"):  # file, abstract
                    try:
                        s.connect(path)
                        return True
                    except OSError:
                        continue
            return False
        with socket.create_connection((host, 6000 + n), timeout=timeout):
            return True
    except OSError:
        return False


def require_display() -> None:
    """Raise :class:`NoDisplayError` unless a window can be opened (X11/Wayland on Linux)."""
    driver = os.environ.get("SDL_VIDEODRIVER", "")
    if driver in HEADLESS_DRIVERS or not sys.platform.startswith("linux"):
        return
    x, wayland = os.environ.get("DISPLAY"), os.environ.get("WAYLAND_DISPLAY")
    if not (x or wayland):
        raise NoDisplayError(f"no display for the driving window (DISPLAY is not set): {HOW}")
    if x and not wayland:
        if not x_server_reachable(x):
            raise NoDisplayError(f"no X server answers at DISPLAY={x} for the driving window: {HOW}")
        os.environ.setdefault("SDL_VIDEODRIVER", "x11")  # no fallback to drivers that may hang
