"""A person drives with the arrow keys in a pygame window: the human keyboard recorder.

The window (X window class ``memrl``, under 1366x768) shows the full scene (the env's own
picture, enlarged, with the target lane named on it and the car's heading and path drawn
ahead of it) beside the agent's 84x84 view (its newest stacked frame, enlarged), with the
episode count, the speed and curvature, and a legend of the keys. Each step waits for the
step rate, reads the keys and returns the action; that action is what the env executes and
what the recorder stores. What the keys mean is :mod:`memrl.modules.human_controls`
(``controls: assisted`` by default, or ``literal``).

Keys: arrows drive; P or Space pauses and continues; Esc or closing the window ends the
recording (the episode under way is dropped). A key tapped between two steps counts for the
next step even if released before it. With ``wait_for_start``, each episode waits for a key.

Headless use (tests): ``SDL_VIDEODRIVER=dummy`` and synthetic events posted with
``pygame.event.post``. Key state is tracked from events, not ``pygame.key.get_pressed()``,
which synthetic events do not change.
"""

from __future__ import annotations

import os
from typing import Any

import cv2
import numpy as np

from memrl.envs.lane_change import LaneChangeEnv
from memrl.envs.render import arc_points
from memrl.modules.display import WINDOW_CLASS, require_display
from memrl.modules.human_controls import CONTROLS, action_from_keys, assisted_action
from memrl.modules.policy import DrivingPolicy, StopRecording

__all__ = ["KeyboardDriver", "action_from_keys", "assisted_action"]

LEGEND = {
    "assisted": ["Left/Right held: curve that way",
                 "  released: steer back to straight",
                 "Up/Down held: faster/slower; released: keep"],
    "literal": ["Left/Right: +1 curvature step per step",
                "  (it stays when released: steer back!)",
                "Up/Down: +-0.1 m/s per step"],
}
PATH_COLOUR = (255, 0, 255)
"""The car's path at its present curvature in the scene panel (a shade the scene never uses)."""


class KeyboardDriver(DrivingPolicy):
    """Human driver: arrow keys -> one of the 9 actions at a fixed step rate.

    Args:
        fps: action steps per second (10 is real time for ``dt`` = 0.1 s); 0 does not wait.
        controls: ``assisted`` or ``literal`` (:mod:`memrl.modules.human_controls`).
        turn_heading: assisted: heading wanted while Left/Right is held [rad].
        turn_curvature: assisted: largest curvature it steers to [rad/m].
        scene_scale: enlargement of the full-scene picture.
        view_scale: enlargement (integer, nearest neighbour) of the agent's 84x84 view.
        path_length: length of the path drawn ahead of the car in the scene panel [m].
        wait_for_start: hold each episode at its first step until an arrow key is pressed.
        caption: window title.
    """

    needs_render = True
    """The recorder must build the env with ``render_mode='rgb_array'`` (full-scene picture)."""

    def __init__(self, *, fps: float = 10.0, controls: str = "assisted", turn_heading: float = 0.12,
                 turn_curvature: float = 0.02, scene_scale: float = 1.2,
                 view_scale: int = 3, path_length: float = 30.0, wait_for_start: bool = True,
                 caption: str = "memrl: drive with the arrow keys") -> None:
        if fps < 0:
            raise ValueError(f"KeyboardDriver 'fps': must be >= 0, got {fps}")
        if controls not in CONTROLS:
            raise ValueError(f"KeyboardDriver 'controls': one of {list(CONTROLS)}, got {controls!r}")
        self.fps, self.controls = fps, controls
        self.assist = {"turn_heading": turn_heading, "turn_curvature": turn_curvature}
        self.scene_scale, self.view_scale = scene_scale, int(view_scale)
        self.path_length = path_length
        self.wait_for_start = wait_for_start
        self.caption = caption
        self.held: set[str] = set()
        self.tapped: set[str] = set()
        """Keys pressed since the last step (they count once even if already released)."""
        self.executed: list[int] = []
        """Every action returned (and so executed), in order, across episodes."""
        self.progress: tuple[int, int, int] | None = None
        """(episode number from 1, episodes planned, kept so far), set by the recorder."""
        self.kept_label = "kept so far"
        self.paused = False
        self._pg: Any = None
        self._screen: Any = None
        self._clock: Any = None
        self._font: Any = None
        self._keymap: dict[int, str] = {}
        self._waiting = False
        require_display()  # refuse at start, before any recording, when no window can open

    # ----------------------------------------------------------------------- window
    def _open(self, scene: np.ndarray, view_shape: tuple[int, int]) -> None:
        os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
        os.environ["SDL_VIDEO_X11_WMCLASS"] = WINDOW_CLASS
        import pygame  # lazy: pygame (from pygame-ce) opens nothing until needed

        self._pg = pygame
        pygame.display.init()
        pygame.font.init()
        self._keymap = {pygame.K_UP: "up", pygame.K_DOWN: "down",
                        pygame.K_LEFT: "left", pygame.K_RIGHT: "right"}
        sh, sw = (int(round(d * self.scene_scale)) for d in scene.shape[:2])
        vh, vw = (d * self.view_scale for d in view_shape)
        self._screen = pygame.display.set_mode((sw + max(vw, 330) + 30, max(sh, vh + 260) + 20))
        pygame.display.set_caption(self.caption)
        self._clock = pygame.time.Clock()
        self._font = pygame.font.Font(None, 22)

    def close(self) -> None:
        """Close the window (the recorder calls this at the end)."""
        if self._pg is not None:
            self._pg.display.quit()
            self._pg = self._screen = None

    def _blit(self, img: np.ndarray, scale: float, pos: tuple[int, int]) -> None:
        """Draw an (H, W[, 3]) uint8 picture, enlarged, with its top-left corner at ``pos``."""
        big = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
        if big.ndim == 2:
            big = np.repeat(big[:, :, None], 3, axis=2)
        # pygame surfaces are indexed (x, y): transpose rows and columns
        self._screen.blit(self._pg.surfarray.make_surface(big.transpose(1, 0, 2)), pos)

    def _to_scene_px(self, env: LaneChangeEnv, xy: np.ndarray) -> np.ndarray:
        """World points ``[..., (x, y)]`` [m] -> window pixels ``[..., (px, py)]`` in the scene panel."""
        s, car = env.cfg.scene, env.vehicle.position
        col = 0.5 * s.width + (xy[..., 1] - car[1]) / s.lateral_scale
        row = 0.5 * s.height - (xy[..., 0] - car[0]) / s.longitudinal_scale
        return np.stack([10 + col * self.scene_scale, 10 + row * self.scene_scale], axis=-1)

    def _draw_scene_marks(self, env: LaneChangeEnv) -> None:
        """The target lane named at the top of the scene, and the car's path ahead."""
        pg, car = self._pg, env.vehicle
        lane_y = env.target_lane * env.cfg.lane_width
        px = self._to_scene_px(env, np.array([car.position[0], lane_y]))
        label = self._font.render("TARGET", True, (255, 255, 255), (0, 90, 0))
        x = int(min(max(px[0] - label.get_width() / 2, 10),
                    10 + env.cfg.scene.width * self.scene_scale - label.get_width()))
        self._screen.blit(label, (x, 14))
        if self.path_length > 0:
            state = np.array([*car.position, car.heading, car.curvature], dtype=np.float64)
            pts = self._to_scene_px(env, arc_points(state, np.linspace(0.0, self.path_length, 16)))
            pg.draw.lines(self._screen, PATH_COLOUR, False, [tuple(p) for p in pts], 2)

    def _draw(self, env: LaneChangeEnv, pixels: np.ndarray, scene: np.ndarray, lines: list[str]) -> None:
        self._screen.fill((20, 20, 20))
        self._blit(scene, self.scene_scale, (10, 10))
        self._draw_scene_marks(env)
        x0 = 20 + int(round(scene.shape[1] * self.scene_scale))
        self._blit(pixels[-1], self.view_scale, (x0, 10))
        y = 20 + pixels.shape[-2] * self.view_scale
        for line in lines:
            self._screen.blit(self._font.render(line, True, (230, 230, 230)), (x0, y))
            y += 21
        self._pg.display.flip()

    def _status(self, env: LaneChangeEnv) -> list[str]:
        car = env.vehicle
        lines = []
        if self.progress is not None:
            k, n, kept = self.progress
            lines.append(f"episode {k} of {n}   {self.kept_label} {kept}")
        lines += [f"step {env.steps}/{env.cfg.duration}   target: lane {env.target_lane + 1} "
                  f"of {env.cfg.lanes_count} (from left)",
                  f"speed {car.speed:.1f} m/s   curvature {car.curvature:+.2f} rad/m",
                  f"heading {np.degrees(car.heading):+.0f} deg   path: magenta line",
                  f"controls: {self.controls}   {self.fps:g} steps/s",
                  *LEGEND[self.controls],
                  "P or Space: pause   Esc: stop (finished episodes kept)"]
        return lines

    # ------------------------------------------------------------------------ keys
    def _pump(self) -> None:
        """Apply pending window events to the key state; Esc or closing the window stops."""
        pg = self._pg
        for event in pg.event.get():
            if event.type == pg.QUIT or (event.type == pg.KEYDOWN and event.key == pg.K_ESCAPE):
                raise StopRecording("stopped from the keyboard")
            if event.type == pg.KEYDOWN and event.key in (pg.K_p, pg.K_SPACE):
                self.paused = not self.paused
                continue
            name = self._keymap.get(getattr(event, "key", None))  # type: ignore[arg-type]
            if name is None:
                continue
            if event.type == pg.KEYDOWN:
                self.held.add(name)
                self.tapped.add(name)
                self._waiting = False
            elif event.type == pg.KEYUP:
                self.held.discard(name)

    def _hold(self, env: LaneChangeEnv, pixels: np.ndarray, scene: np.ndarray, status: list[str]) -> None:
        """Wait (drawing, reading keys) while paused or before an episode's first key."""
        while self._waiting or self.paused:
            note = "PAUSED: P or Space to go on" if self.paused else "press an arrow key to start"
            self._draw(env, pixels, scene, [*status, note])
            self._pump()
            self._clock.tick(30)

    # -------------------------------------------------------------------------- API
    def reset(self, env: LaneChangeEnv) -> None:
        self.tapped.clear()  # held keys stay held: no new KEYDOWN comes for a key kept down
        self._waiting = self.wait_for_start

    def action(self, env: LaneChangeEnv, held: set[str]) -> int:
        """The action for the held keys in the env's present state (the controls' mapping)."""
        if self.controls == "literal":
            return action_from_keys(held)
        car = env.vehicle
        return assisted_action(held, car.heading, car.curvature, car.speed,
                               curvature_step=env.cfg.curvature_step, dt=env.cfg.dt, **self.assist)

    def act(self, env: LaneChangeEnv, pixels: np.ndarray) -> int:
        scene = env.render()
        if scene is None:
            raise RuntimeError("KeyboardDriver needs the env built with render_mode='rgb_array'")
        if self._screen is None:
            self._open(scene, pixels.shape[-2:])
        status = self._status(env)
        self._hold(env, pixels, scene, status)
        self._draw(env, pixels, scene, status)
        if self.fps > 0:
            self._clock.tick(self.fps)  # the human reacts to the picture during this wait
        self._pump()
        self._hold(env, pixels, scene, status)
        action = self.action(env, self.held | self.tapped)
        self.tapped.clear()
        self.executed.append(action)
        return action
