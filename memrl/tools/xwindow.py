"""The recorder's real X window from outside: find it, read its pixels, press its keys.

Keys go through ``xdotool keydown/keyup`` (XTEST: real X key events, as a keyboard makes),
pixels through Pillow's X screen grab. Used by the window bot and the real-window test.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time

import numpy as np

from memrl.modules.display import WINDOW_CLASS

KEYSYMS = {"up": "Up", "down": "Down", "left": "Left", "right": "Right"}


def have_tools() -> bool:
    """Xvfb and xdotool are installed."""
    return shutil.which("Xvfb") is not None and shutil.which("xdotool") is not None


class XWindow:
    """The recorder's window on ``display`` (``:N``), found by its class ``memrl``."""

    def __init__(self, display: str, timeout: float = 120.0, poll: float = 0.2,
                 proc: subprocess.Popen | None = None) -> None:
        """Wait for the window; with ``proc`` (the recorder), stop as soon as it has exited."""
        self.display = display
        self.env = {**os.environ, "DISPLAY": display}
        deadline = time.time() + timeout
        while True:
            found = self._xdotool("search", "--classname", WINDOW_CLASS, check=False).split()
            if found:
                self.wid = found[0]
                break
            if proc is not None and proc.poll() is not None:
                raise RuntimeError(f"the recorder exited with code {proc.returncode} before its window "
                                   f"of class {WINDOW_CLASS} appeared on {display}")
            if time.time() > deadline:
                raise TimeoutError(f"no window of class {WINDOW_CLASS} on {display} in {timeout:.0f} s "
                                   f"(X server answers: {self.server_answers()})")
            time.sleep(poll)
        self.held: set[str] = set()
        self._xdotool("windowfocus", "--sync", self.wid, check=False)

    def _xdotool(self, *args: str, check: bool = True) -> str:
        res = subprocess.run(["xdotool", *args], env=self.env, capture_output=True, text=True)
        if check and res.returncode:
            raise RuntimeError(f"xdotool {' '.join(args)}: {res.stderr.strip()}")
        return res.stdout

    def server_answers(self) -> bool:
        """Whether the X server at this display answers a query (``xdotool getdisplaygeometry``)."""
        res = subprocess.run(["xdotool", "getdisplaygeometry"], env=self.env, capture_output=True)
        return res.returncode == 0

    def alive(self) -> bool:
        return bool(self._xdotool("search", "--classname", WINDOW_CLASS, check=False).split())

    def geometry(self) -> tuple[int, int, int, int]:
        """(x, y, width, height) of the window on the screen [px]."""
        out = self._xdotool("getwindowgeometry", "--shell", self.wid)
        v = dict(line.split("=", 1) for line in out.split())
        return int(v["X"]), int(v["Y"]), int(v["WIDTH"]), int(v["HEIGHT"])

    def grab(self) -> np.ndarray:
        """The window's pixels ``(H, W, 3)`` uint8, as shown on the screen."""
        from PIL import ImageGrab

        x, y, w, h = self.geometry()
        return np.asarray(ImageGrab.grab(bbox=(x, y, x + w, y + h), xdisplay=self.display))[..., :3]

    def hold(self, keys: set[str]) -> None:
        """Hold exactly ``keys`` (arrow names) down: press the new ones, release the others."""
        up = [KEYSYMS[k] for k in self.held - keys]
        down = [KEYSYMS[k] for k in keys - self.held]
        if up:
            self._xdotool("keyup", *up, check=False)
        if down:
            self._xdotool("keydown", *down, check=False)
        self.held = set(keys)

    def tap(self, key: str) -> None:
        self._xdotool("key", KEYSYMS.get(key, key), check=False)


def start_xvfb(size: str = "1366x768x24", timeout: float = 20.0) -> tuple[subprocess.Popen, str]:
    """An Xvfb server on a display number it finds free itself (``-displayfd``: no clash with
    servers of other users, whose abstract sockets a chosen number could meet); returns the
    process (the caller terminates it) and its display (``:N``)."""
    read, write = os.pipe()
    proc = subprocess.Popen(["Xvfb", "-displayfd", str(write), "-screen", "0", size, "-nolisten", "tcp"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, pass_fds=(write,))
    os.close(write)
    deadline, text = time.time() + timeout, b""
    try:
        while not text.endswith(b"\n"):
            if proc.poll() is not None or time.time() > deadline:
                proc.kill()
                raise RuntimeError("Xvfb did not start")
            chunk = os.read(read, 16)
            if not chunk:
                time.sleep(0.05)
            text += chunk
    finally:
        os.close(read)
    return proc, f":{int(text)}"
