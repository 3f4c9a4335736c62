"""The recorder in a real X window: Xvfb, real X key events (xdotool), the window's own pixels.

Skipped where Xvfb or xdotool is missing (``.ci/run`` installs both)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from memrl.data.demos import load_demos, read_metadata
from memrl.envs.lane_change import LaneChangeEnv
from memrl.modules.human_controls import assisted_action
from memrl.tools.window_bot import read_scene
from memrl.tools.xwindow import XWindow, have_tools, start_xvfb

ROOT = Path(__file__).resolve().parents[1]
needs_x = pytest.mark.skipif(not have_tools(), reason="needs Xvfb and xdotool (apt-get install xvfb xdotool)")


def record_cmd(out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "memrl.record", "demos=human", "episodes=1", "keep=stable",
            "env.vehicles_count=0", "env.initial_lane=non_goal", "env.duration=90", "seed=3",
            "demos.person=test", f"out={out}", "progress=false", f"hydra.run.dir={out.parent / 'hydra'}",
            *extra]


@needs_x
def test_a_lane_change_driven_with_real_keys_is_stored_as_the_assisted_actions(tmp_path):
    xvfb, display = start_xvfb()
    out = tmp_path / "demos"
    env = {k: v for k, v in os.environ.items() if k != "SDL_VIDEODRIVER"}  # conftest's offscreen
    env.update(DISPLAY=display, PYTHONPATH=str(ROOT))
    log = tmp_path / "recorder.log"  # a file, not a pipe: unread output can never block the recorder
    with open(log, "w") as sink:
        proc = subprocess.Popen(record_cmd(out), cwd=ROOT, env=env, stdout=sink, stderr=subprocess.STDOUT)
    try:
        try:
            win = XWindow(display, timeout=180, proc=proc)
        except (TimeoutError, RuntimeError) as e:
            proc.kill()
            proc.wait()
            pytest.fail(f"{e}; the recorder printed:\n{log.read_text()[-4000:]}")
        x, y, w, h = win.geometry()
        assert w <= 1366 and h <= 768 - 40  # fits a 1366x768 screen with a title bar
        scene = None
        while scene is None:  # the episode waits for a first key, showing its start
            scene = read_scene(win.grab(), look=8.0)
        assert scene.lane != scene.target  # a non-goal start
        side = "right" if scene.target > scene.lane else "left"
        win.hold({side})  # starts the episode, held: curve toward the target lane
        while True:  # a person's eye: release when the path ahead meets the target lane's centre
            s = read_scene(win.grab(), look=8.0)
            if s is not None and s.path_col is not None and \
                    (s.path_col - s.lanes[s.target]) * (1 if side == "right" else -1) > -0.2 * s.ppm:
                break
            assert proc.poll() is None, log.read_text()
        win.hold(set())
        proc.wait(timeout=120)
        text = log.read_text()
    finally:
        proc.kill()
        xvfb.terminate()
        xvfb.wait()
    assert proc.returncode == 0, text
    assert "kept (stable) 1 episodes" in text  # no collision, target lane reached: kept
    meta = read_metadata(out)
    assert meta["person"] == "test"
    actions = load_demos(out)["action"].reshape(-1).tolist()
    # replay: each stored action is what the assisted mode issues for the keys held then
    # (the side key for the first k steps, none after), and the car ends in the target lane
    env = LaneChangeEnv(config=meta["env_config"])
    env.reset(seed=3)
    car, cfg = env.vehicle, env.cfg
    options = []
    for a in actions:
        want = {k: assisted_action(held, car.heading, car.curvature, car.speed,
                                   curvature_step=cfg.curvature_step, dt=cfg.dt)
                for k, held in (("held", {side}), ("none", set()))}
        options.append({k for k, v in want.items() if v == a})
        env.step(a)
    assert all(options), [i for i, o in enumerate(options) if not o]
    switch = next(i for i, o in enumerate(options) if "held" not in o)
    assert switch >= 5 and all("none" in o for o in options[switch:])
    assert env.current_lane() == env.target_lane and abs(car.heading) < 0.01
    assert np.isclose(car.curvature, 0.0)


@pytest.mark.parametrize("display", [None, ":1999"])
def test_no_usable_display_is_refused_at_start_in_one_line(tmp_path, display):
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "SDL_VIDEODRIVER")}
    if display is not None:
        env["DISPLAY"] = display  # nothing listens there
    res = subprocess.run(record_cmd(tmp_path / "demos"), cwd=ROOT, env={**env, "PYTHONPATH": str(ROOT)},
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "xvfb-run" in lines[0], res.stderr
    assert "display" in lines[0].lower() and not (tmp_path / "demos").exists()


@needs_x
def test_waiting_for_the_window_stops_when_the_recorder_has_exited():
    xvfb, display = start_xvfb()
    try:
        proc = subprocess.Popen([sys.executable, "-c", "raise SystemExit(3)"])
        with pytest.raises(RuntimeError, match="exited with code 3 before its window"):
            XWindow(display, timeout=60, proc=proc)
    finally:
        xvfb.terminate()
        xvfb.wait()
