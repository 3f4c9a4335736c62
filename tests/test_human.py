"""The keyboard recorder, headless: SDL's dummy video driver and synthetic key events."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from memrl.data.demos import load_demos
from memrl.envs.torchrl_env import make_env, unwrap
from memrl.envs.vehicles import IDLE, action_index
from memrl.modules.human import KeyboardDriver, action_from_keys
from memrl.modules.human_controls import assisted_action
from memrl.modules.policy import PolicyModule
from memrl.record import record


@pytest.fixture
def pg(monkeypatch):
    """pygame on the dummy video driver; the display is closed afterwards."""
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    monkeypatch.setenv("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    import pygame

    pygame.display.init()
    pygame.event.clear()
    yield pygame
    pygame.display.quit()


def press(pg, *keys: int) -> None:
    for key in keys:
        pg.event.post(pg.event.Event(pg.KEYDOWN, key=key))


def release(pg, *keys: int) -> None:
    for key in keys:
        pg.event.post(pg.event.Event(pg.KEYUP, key=key))


@pytest.mark.parametrize(
    ("held", "signs"),
    [((), (0, 0)), (("up",), (1, 0)), (("down",), (-1, 0)), (("left",), (0, -1)),
     (("right",), (0, 1)), (("up", "left"), (1, -1)), (("up", "right"), (1, 1)),
     (("down", "left"), (-1, -1)), (("down", "right"), (-1, 1)), (("up", "down"), (0, 0)),
     (("left", "right", "up"), (1, 0))],
)
def test_arrow_keys_map_to_the_nine_actions(held, signs):
    assert action_from_keys(set(held)) == action_index(*signs)


def test_synthetic_key_presses_are_the_executed_actions(pg):
    env = make_env({"vehicles_count": 0, "target_lane": 1}, seed=0, render_mode="rgb_array")
    driver = KeyboardDriver(fps=0, wait_for_start=False, controls="literal")
    module = PolicyModule(driver, unwrap(env))
    td = env.reset()
    car = unwrap(env).vehicle
    script = [  # (events before the step, expected action)
        (lambda: press(pg, pg.K_UP), action_index(1, 0)),
        (lambda: None, action_index(1, 0)),  # still held
        (lambda: (release(pg, pg.K_UP), press(pg, pg.K_RIGHT)), action_index(0, 1)),
        (lambda: press(pg, pg.K_DOWN), action_index(-1, 1)),
        (lambda: release(pg, pg.K_DOWN, pg.K_RIGHT), IDLE),
        (lambda: (press(pg, pg.K_LEFT), release(pg, pg.K_LEFT)), action_index(0, -1)),  # a tap
        (lambda: None, IDLE),  # the tap counted once
        (lambda: press(pg, pg.K_a, pg.K_z), IDLE),  # other keys do nothing
    ]
    taken = []
    for events, expected in script:
        events()
        speed, curvature = car.speed, car.curvature
        td = module(td)
        taken.append(int(td["action"]))
        td = env.step(td)
        ds, dk = np.sign(round(car.speed - speed, 6)), np.sign(round(car.curvature - curvature, 6))
        assert action_index(int(ds), int(dk)) == expected  # what the car actually did
        td = td["next"]
    assert taken == [e for _, e in script] == driver.executed
    # the window shows the scene and, beside it, the agent's newest frame enlarged 4x
    screen = pg.surfarray.array3d(pg.display.get_surface()).transpose(1, 0, 2)  # (H, W, 3)
    scene_w = int(round(unwrap(env).cfg.scene.width * driver.scene_scale))
    view = screen[10:10 + 252, 20 + scene_w:20 + scene_w + 252, 0]
    assert view.std() > 5 and screen[10:600, 10:10 + scene_w].std() > 5
    assert screen.shape[0] <= 700 and screen.shape[1] <= 1300  # fits a 1366x768 screen
    driver.close()


def test_view_in_the_window_is_the_observation(pg):
    env = make_env({"vehicles_count": 3}, seed=2, render_mode="rgb_array")
    driver = KeyboardDriver(fps=0, wait_for_start=False, view_scale=3)
    td = env.reset()
    driver.act(unwrap(env), td["pixels"].numpy())
    screen = pg.surfarray.array3d(pg.display.get_surface()).transpose(1, 0, 2)
    x0 = 20 + int(round(unwrap(env).cfg.scene.width * driver.scene_scale))
    view = screen[10:10 + 252:3, x0:x0 + 252:3, 0]
    assert np.array_equal(view, td["pixels"][-1].numpy())
    driver.close()


def test_episode_waits_for_a_first_key_when_asked(pg):
    env = make_env({"vehicles_count": 0}, seed=0, render_mode="rgb_array")
    driver = KeyboardDriver(fps=0, wait_for_start=True)
    td = env.reset()
    driver.reset(unwrap(env))
    press(pg, pg.K_DOWN)  # the key that starts the episode is also its first action
    assert driver.act(unwrap(env), td["pixels"].numpy()) == action_index(-1, 0)
    driver.close()


def test_record_command_stores_the_keyboard_actions(pg, compose_cfg, tmp_path):
    out = tmp_path / "human"
    cfg = compose_cfg("record", ["demos=human", "demos.policy.fps=0", "demos.policy.wait_for_start=false",
                                 "demos.policy.controls=literal", "episodes=2", "keep=all",
                                 "env.vehicles_count=0", f"out={out}", "progress=false"])
    press(pg, pg.K_RIGHT)  # held for the whole recording: the car turns into the right wall
    summary = record(cfg)
    assert summary.recorded["episodes"] == 2 and summary.recorded["survival"] == 0
    td = load_demos(out, cfg.env)
    assert torch.all(td["action"] == action_index(0, 1))
    assert td["next", "terminated"][-1].item() and td.shape[0] == summary.kept["transitions"]


def test_escape_stops_and_drops_the_unfinished_episode(pg, compose_cfg, tmp_path):
    cfg = compose_cfg("record", ["demos=human", "demos.policy.fps=0", "demos.policy.wait_for_start=false",
                                 "episodes=3", "keep=all", f"out={tmp_path / 'none'}", "progress=false"])
    press(pg, pg.K_UP, pg.K_ESCAPE)
    from memrl.stop import Stopped

    with pytest.raises(Stopped, match="before any episode finished; nothing saved") as stop:
        record(cfg)
    assert stop.value.status == 130
    assert not (tmp_path / "none").exists()


def test_steps_are_paced_at_the_configured_rate(pg, monkeypatch):
    ticks = []

    class FakeClock:  # records the pacing instead of sleeping (no timed assertions)
        def tick(self, fps: float = 0) -> int:
            ticks.append(fps)
            return 0

    monkeypatch.setattr(pg.time, "Clock", FakeClock)
    env = make_env({"vehicles_count": 0}, seed=0, render_mode="rgb_array")
    driver = KeyboardDriver(fps=25, wait_for_start=False)
    td = env.reset()
    for _ in range(3):
        driver.act(unwrap(env), td["pixels"].numpy())
    assert ticks == [25, 25, 25]
    driver.close()
    with pytest.raises(ValueError, match="fps"):
        KeyboardDriver(fps=-1)


def test_assisted_keys_turn_then_straighten_without_overshoot(pg):
    env = make_env({"vehicles_count": 0, "target_lane": 1, "initial_lane": "non_goal"}, seed=0,
                   render_mode="rgb_array")
    driver = KeyboardDriver(fps=0, wait_for_start=False)
    module = PolicyModule(driver, unwrap(env))
    td = env.reset()
    car = unwrap(env).vehicle
    press(pg, pg.K_RIGHT)
    headings = []
    for step in range(60):
        if step == 15:
            release(pg, pg.K_RIGHT)
        held = {"right"} if step < 15 else set()
        expected = assisted_action(held, car.heading, car.curvature, car.speed,
                                   curvature_step=0.01, dt=0.1)
        td = module(td)
        assert int(td["action"]) == expected
        td = env.step(td)["next"]
        headings.append(car.heading)
    assert max(headings) == pytest.approx(0.12, abs=0.02)  # curved right up to turn_heading
    assert abs(headings[-1]) < 0.005 and car.curvature == 0  # released: straight again
    assert min(headings) > -0.005  # without overshooting to the other side
    driver.close()


def test_assisted_speed_changes_only_while_held():
    held_up = assisted_action({"up"}, 0.0, 0.0, 10.0, curvature_step=0.01)
    assert held_up == action_index(1, 0)
    assert assisted_action(set(), 0.0, 0.0, 10.0, curvature_step=0.01) == IDLE
    assert assisted_action({"down", "left"}, 0.0, 0.0, 10.0, curvature_step=0.01) == action_index(-1, -1)


def test_pause_key_holds_the_step(pg):
    env = make_env({"vehicles_count": 0}, seed=0, render_mode="rgb_array")
    driver = KeyboardDriver(fps=0, wait_for_start=False)
    td = env.reset()
    driver.act(unwrap(env), td["pixels"].numpy())  # opens the window
    press(pg, pg.K_p)
    pg.event.post(pg.event.Event(pg.KEYDOWN, key=pg.K_ESCAPE))  # Esc still stops while paused
    from memrl.modules.policy import StopRecording

    with pytest.raises(StopRecording):
        driver.act(unwrap(env), td["pixels"].numpy())
    assert driver.paused
    driver.close()


def test_no_display_is_refused_in_one_line(monkeypatch):
    from memrl.modules.display import NoDisplayError

    monkeypatch.delenv("SDL_VIDEODRIVER", raising=False)
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(NoDisplayError, match="xvfb-run"):
        KeyboardDriver()


def test_person_is_in_the_dataset_and_training_logs_what_it_loaded(pg, compose_cfg, tmp_path, caplog):
    from memrl.data.demos import read_metadata
    from memrl.train import prior_knowledge

    out = tmp_path / "ann"
    cfg = compose_cfg("record", ["demos=human", "demos.person=ann", "demos.policy.fps=0",
                                 "demos.policy.wait_for_start=false", "episodes=1", "keep=all",
                                 "env.duration=20", f"out={out}", "progress=false"])
    summary = record(cfg)
    assert read_metadata(out)["person"] == "ann"
    train_cfg = compose_cfg("train", ["+mode=A", f"mode.demos_path={out}", "env.duration=20"])
    with caplog.at_level("INFO", logger="memrl.train"):
        td = prior_knowledge(train_cfg)
    assert td.shape[0] == summary.kept["transitions"]
    assert f"prior knowledge: {out.resolve()} ({td.shape[0]} transitions)" in caplog.text


def test_human_recording_goes_on_in_a_second_sitting(pg, compose_cfg, tmp_path, monkeypatch):
    from memrl.data.demos import read_metadata
    from memrl.stop import Stopped

    out = tmp_path / "ann"
    args = ["demos=human", "demos.policy.fps=0", "demos.policy.wait_for_start=false"]
    real, calls = KeyboardDriver.act, {"n": 0}

    def act(self, env, pixels):  # Esc in the second episode of the first sitting
        calls["n"] += 1
        if calls["n"] == 25:
            pg.event.post(pg.event.Event(pg.KEYDOWN, key=pg.K_ESCAPE))
        return real(self, env, pixels)

    monkeypatch.setattr(KeyboardDriver, "act", act)
    with pytest.raises(Stopped) as stop:
        record(compose_cfg("record", [*args, "demos.person=ann", "episodes=2", "keep=all",
                                      "env.duration=20", f"out={out}", "progress=false"]))
    assert str(stop.value).endswith(f"go on with: python -m memrl.record demos=human resume={out}")
    monkeypatch.setattr(KeyboardDriver, "act", real)
    summary = record(compose_cfg("record", [*args, f"resume={out}", "progress=false"]))
    meta = read_metadata(out)
    assert summary.recorded["episodes"] == 2 and meta["person"] == "ann"
    assert [e["seed"] for e in meta["episodes"]] == [0, 1] and load_demos(out).shape[0] == 40
