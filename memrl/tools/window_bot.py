"""A stand-in for a person: drives the recorder through its real X window, from its pixels only.

It reads the scene panel as a person looks at it (the lanes, the target lane's shade, the
other cars, its own car and the magenta path drawn ahead of it) and holds arrow keys with
real X key events (``xdotool``). It knows no world state and no config; it does not read
the text. Used to choose the recorder's default step rate and to check that the controls
can be driven (``tests/test_human_window.py``)::

    python -m memrl.tools.window_bot episodes=10 fps=10 controls=assisted

starts Xvfb, runs ``python -m memrl.record demos=human`` on non-goal starts among 0-5 cars,
drives it, and prints the recorder's summary (``kept (stable) N episodes``).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from memrl.tools.xwindow import XWindow, start_xvfb

BACKGROUND = (20, 20, 20)
ROAD, TARGET = (64, 64, 64), (80, 104, 80)
AGENT, PATH = (255, 220, 0), (255, 0, 255)
OTHERS = ((30, 200, 30), (90, 190, 255))
LANE_WIDTH = 4.0
"""[m]: what a driver knows of the road, to read distances off the picture."""


def _mask(img: np.ndarray, colour: tuple[int, int, int]) -> np.ndarray:
    return np.all(img == np.array(colour, dtype=np.uint8), axis=-1)


@dataclass
class Scene:
    """What the bot sees in the scene panel (pixels; rows grow backwards, columns rightwards)."""

    car: tuple[float, float]
    """(row, column) of its car's centre."""
    lanes: list[float]
    """Lane centre columns, left to right."""
    target: int
    """Index of the target lane."""
    ppm: float
    """Pixels per metre."""
    others: np.ndarray
    """(row, column) of every other-car pixel."""
    path_col: float | None
    """Column of the path ``look`` metres ahead (None: not visible)."""

    @property
    def lane(self) -> int:
        return int(np.argmin([abs(c - self.car[1]) for c in self.lanes]))

    def clear(self, lane: int, ahead: float, behind: float) -> bool:
        """No other car in ``lane`` from ``behind`` m behind to ``ahead`` m ahead of the car."""
        return self.nearest(lane, ahead, behind) is None

    def nearest(self, lane: int, ahead: float, behind: float) -> float | None:
        """Signed distance [m] (+ ahead) to the nearest other-car pixel in ``lane`` within the range."""
        half = 0.5 * LANE_WIDTH * self.ppm
        rows = self.others[np.abs(self.others[:, 1] - self.lanes[lane]) < half - 1, 0]
        d = (self.car[0] - rows) / self.ppm
        d = d[(d < ahead) & (d > -behind)]
        return None if d.size == 0 else float(d[np.argmin(np.abs(d))])


def read_scene(window: np.ndarray, look: float) -> Scene | None:
    """The scene panel of the recorder's window (its left picture), or None if no car shows."""
    cols = np.where(np.all(window[20:-20] == np.array(BACKGROUND, np.uint8), axis=(0, 2)))[0]
    right = int(cols[cols > 15][0]) if np.any(cols > 15) else window.shape[1]
    panel = window[30:-12, 10:right]  # below the TARGET label
    agent = np.argwhere(_mask(panel, AGENT))
    tgt, road = _mask(panel, TARGET), _mask(panel, ROAD)
    if len(agent) == 0 or not tgt.any():
        return None
    share = 0.3 * panel.shape[0]
    t_cols = np.where(tgt.sum(0) > share)[0]
    r_cols = np.where((tgt | road).sum(0) > share)[0]
    if len(t_cols) == 0 or len(r_cols) == 0:
        return None
    lane_px = t_cols[-1] - t_cols[0] + 1 + 1  # plus the dashed divider's column
    n = max(1, int(round((r_cols[-1] - r_cols[0] + 1) / lane_px)))
    width = (r_cols[-1] - r_cols[0] + 1) / n
    lanes = [r_cols[0] + width * (i + 0.5) for i in range(n)]
    t_centre = 0.5 * (t_cols[0] + t_cols[-1])
    target = int(np.argmin([abs(c - t_centre) for c in lanes]))
    ppm = width / LANE_WIDTH
    car = (float(agent[:, 0].mean()), float(agent[:, 1].mean()))
    others = np.argwhere(np.any([_mask(panel, c) for c in OTHERS], axis=0))
    path = np.argwhere(_mask(panel, PATH))
    row = car[0] - look * ppm
    near = path[np.abs(path[:, 0] - row) < 3]
    return Scene(car, lanes, target, ppm, others, float(near[:, 1].mean()) if len(near) else None)


@dataclass
class Bot:
    """The rules: change to the target lane when its gap is clear, keep distance, centre the car."""

    look: float = 8.0
    """[m] ahead: where the path is compared with the lane wanted."""
    tolerance: float = 0.3
    """[m] of that comparison that needs no steering."""
    gap_ahead: float = 16.0
    gap_behind: float = 20.0
    follow: float = 22.0
    """[m]: slow down when a car ahead in the lane is nearer."""
    pushed: float = 9.0
    """[m]: speed up when a car behind in the lane is nearer (and none is ahead)."""
    speed_room: float = 40.0
    """Speed steps it may add or take away from an episode's start speed (it counts what it pressed)."""
    changing: bool = False
    net: float = 0.0
    """Speed steps pressed so far in this episode (up minus down), from the time keys were held."""

    def new_episode(self) -> None:
        self.changing, self.net = False, 0.0

    def keys(self, s: Scene) -> set[str]:
        keys: set[str] = set()
        lane = s.lane
        want = lane
        if lane != s.target:
            step = 1 if s.target > lane else -1
            nxt = lane + step
            if self.changing or s.clear(nxt, self.gap_ahead, self.gap_behind):
                want, self.changing = nxt, True
            else:
                blocker = s.nearest(nxt, self.gap_ahead, self.gap_behind)
                keys.add("down" if blocker is not None and blocker > 0 else "up")
        else:
            self.changing = False
        ahead = [d for ln in {lane, want} if (d := s.nearest(ln, self.follow, 0.0)) is not None]
        behind = [d for ln in {lane, want} if (d := s.nearest(ln, 0.0, self.pushed)) is not None]
        if ahead and min(ahead) > 0:
            keys.discard("up")
            keys.add("down")
        elif behind:  # a faster car closing from behind: get out of its way
            keys.discard("down")
            keys.add("up")
        if "down" in keys and self.net <= -self.speed_room:
            keys.discard("down")
        if "up" in keys and self.net >= self.speed_room:
            keys.discard("up")
        if s.path_col is not None:
            err = (s.lanes[want] - s.path_col) / s.ppm
            if err > self.tolerance:
                keys.add("right")
            elif err < -self.tolerance:
                keys.add("left")
        return keys


def drive(win: XWindow, proc: subprocess.Popen, look: float = 8.0, period: float = 0.02,
          trace: Any = None, fps: float = 10.0) -> None:
    """Drive until the recorder ends; a still picture for 0.6 s means an episode waits for a key."""
    bot = Bot(look=look)
    last, still_since, tick = None, time.time(), time.time()
    while proc.poll() is None:
        now = time.time()
        bot.net += (int("up" in win.held) - int("down" in win.held)) * (now - tick) * fps
        tick = now
        try:
            img = win.grab()
        except Exception:  # noqa: BLE001 - the window closed between two looks
            break
        s = read_scene(img, look)
        if last is not None and img.shape == last.shape and np.array_equal(img, last):
            if time.time() - still_since > 0.6:
                win.hold(set())
                win.tap("up")  # the episode waits for a first key
                bot.new_episode()
                still_since = time.time()
        else:
            still_since = time.time()
        last = img
        if s is not None:
            keys = bot.keys(s)
            if trace is not None:
                print(f"{time.time():.2f} lane {s.lane} target {s.target} car {s.car[1]:.1f} lanes "
                      f"{[round(c, 1) for c in s.lanes]} path {s.path_col} keys {sorted(keys)}", file=trace)
            win.hold(keys)
        time.sleep(period)
    win.hold(set())


def main(argv: list[str]) -> int:
    opts = {"episodes": "10", "fps": "10", "controls": "assisted", "seed": "0",
            "look": "8", "cars": "[0,5]", "trace": ""}
    for a in argv:
        key, _, value = a.partition("=")
        if key not in opts:
            print(f"error: window_bot: unknown key {key!r}; keys: {', '.join(opts)}", file=sys.stderr)
            return 2
        opts[key] = value
    out = Path(tempfile.mkdtemp(prefix="window_bot_")) / "demos"
    xvfb, display = start_xvfb()
    try:
        cmd = [sys.executable, "-m", "memrl.record", "demos=human", f"episodes={opts['episodes']}",
               f"seed={opts['seed']}", "env.initial_lane=non_goal", f"env.vehicles_count={opts['cars']}",
               f"demos.policy.fps={opts['fps']}", f"demos.policy.controls={opts['controls']}",
               "demos.person=window_bot", f"out={out}", "progress=false",
               f"hydra.run.dir={out.parent / 'hydra'}"]
        log = out.parent / "recorder.log"  # a file, not a pipe: unread output can never block the recorder
        with open(log, "w") as sink:
            proc = subprocess.Popen(cmd, env={**os.environ, "DISPLAY": display},
                                    stdout=sink, stderr=subprocess.STDOUT)
        try:
            win = XWindow(display, timeout=180, proc=proc)
        except (TimeoutError, RuntimeError):
            proc.kill()
            proc.wait()
            print(log.read_text()[-3000:], file=sys.stderr)
            raise
        trace = open(opts["trace"], "w") if opts["trace"] else None  # noqa: SIM115
        drive(win, proc, look=float(opts["look"]), trace=trace, fps=float(opts["fps"]))
        proc.wait()
        text = log.read_text()
        print("\n".join(text.strip().splitlines()[-3:]))  # the recorder's summary
        print(f"window_bot: fps={opts['fps']} controls={opts['controls']} dataset={out}")
        return proc.returncode or 0
    finally:
        xvfb.terminate()
        xvfb.wait()


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
