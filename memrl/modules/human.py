"""A person drives with the arrow keys in a pygame window: the human keyboard recorder.

The window shows the full scene (the env's own OpenCV picture, enlarged) beside the agent's
84x84 view (its newest stacked frame, enlarged), with speed, curvature and the action taken.
Each step waits for the fixed step rate, reads the keys and returns the action; that action is
what the env executes and what the recorder stores.

Keys: Up faster, Down slower, Left/Right curvature toward the left/right of the picture (both
combine, e.g. Up+Left); opposite keys cancel. A key tapped between two steps counts for the
next step even if released before it. Esc or closing the window ends the recording (the
episode under way is dropped). With ``wait_for_start``, each episode waits for a key.

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
from memrl.envs.vehicles import action_index
from memrl.modules.policy import DrivingPolicy, StopRecording

ARROWS = ("up", "down", "left", "right")


def action_from_keys(held: set[str]) -> int:
    """The action index for a set of held arrow names (``up``, ``down``, ``left``, ``right``)."""
    speed = int("up" in held) - int("down" in held)
    curvature = int("right" in held) - int("left" in held)
    return action_index(speed, curvature)


class KeyboardDriver(DrivingPolicy):
    """Human driver: arrow keys -> one of the 9 actions at a fixed step rate.

    Args:
        fps: action steps per second (10 is real time for ``dt`` = 0.1 s); 0 does not wait.
        scene_scale: enlargement of the full-scene picture.
        view_scale: enlargement (integer, nearest neighbour) of the agent's 84x84 view.
        wait_for_start: hold each episode at its first step until an arrow key is pressed.
        caption: window title.
    """

    needs_render = True
    """The recorder must build the env with ``render_mode='rgb_array'`` (full-scene picture)."""

    def __init__(self, *, fps: float = 10.0, scene_scale: float = 1.4, view_scale: int = 4,
                 wait_for_start: bool = True, caption: str = "memrl: drive with the arrow keys") -> None:
        if fps < 0:
            raise ValueError(f"KeyboardDriver 'fps': must be >= 0, got {fps}")
        self.fps = fps
        self.scene_scale = scene_scale
        self.view_scale = int(view_scale)
        self.wait_for_start = wait_for_start
        self.caption = caption
        self.held: set[str] = set()
        self.tapped: set[str] = set()
        """Keys pressed since the last step (they count once even if already released)."""
        self.executed: list[int] = []
        """Every action returned (and so executed), in order, across episodes."""
        self._pg: Any = None
        self._screen: Any = None
        self._clock: Any = None
        self._font: Any = None
        self._keymap: dict[int, str] = {}
        self._waiting = False

    # ----------------------------------------------------------------------- window
    def _open(self, scene: np.ndarray, view_shape: tuple[int, int]) -> None:
        os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
        import pygame  # lazy: pygame (from pygame-ce) opens nothing until needed

        self._pg = pygame
        pygame.display.init()
        pygame.font.init()
        self._keymap = {pygame.K_UP: "up", pygame.K_DOWN: "down",
                        pygame.K_LEFT: "left", pygame.K_RIGHT: "right"}
        sh, sw = (int(round(d * self.scene_scale)) for d in scene.shape[:2])
        vh, vw = (d * self.view_scale for d in view_shape)
        self._screen = pygame.display.set_mode((sw + vw + 30, max(sh, vh + 150) + 20))
        pygame.display.set_caption(self.caption)
        self._clock = pygame.time.Clock()
        self._font = pygame.font.Font(None, 24)

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

    def _draw(self, env: LaneChangeEnv, pixels: np.ndarray, scene: np.ndarray, lines: list[str]) -> None:
        self._screen.fill((20, 20, 20))
        self._blit(scene, self.scene_scale, (10, 10))
        x0 = 20 + int(round(scene.shape[1] * self.scene_scale))
        self._blit(pixels[-1], self.view_scale, (x0, 10))
        y = 20 + pixels.shape[-2] * self.view_scale
        for line in lines:
            self._screen.blit(self._font.render(line, True, (230, 230, 230)), (x0, y))
            y += 24
        self._pg.display.flip()

    # ------------------------------------------------------------------------ keys
    def _pump(self) -> None:
        """Apply pending window events to the key state; Esc or closing the window stops."""
        pg = self._pg
        for event in pg.event.get():
            if event.type == pg.QUIT or (event.type == pg.KEYDOWN and event.key == pg.K_ESCAPE):
                raise StopRecording("stopped from the keyboard")
            name = self._keymap.get(getattr(event, "key", None))  # type: ignore[arg-type]
            if name is None:
                continue
            if event.type == pg.KEYDOWN:
                self.held.add(name)
                self.tapped.add(name)
                self._waiting = False
            elif event.type == pg.KEYUP:
                self.held.discard(name)

    # -------------------------------------------------------------------------- API
    def reset(self, env: LaneChangeEnv) -> None:
        self.tapped.clear()  # held keys stay held: no new KEYDOWN comes for a key kept down
        self._waiting = self.wait_for_start

    def act(self, env: LaneChangeEnv, pixels: np.ndarray) -> int:
        scene = env.render()
        if scene is None:
            raise RuntimeError("KeyboardDriver needs the env built with render_mode='rgb_array'")
        if self._screen is None:
            self._open(scene, pixels.shape[-2:])
        car = env.vehicle
        status = [f"step {env.steps}/{env.cfg.duration}   target lane {env.target_lane}",
                  f"speed {car.speed:.1f} m/s   curvature {car.curvature:+.2f} rad/m",
                  "arrows: drive   Esc: stop"]
        while self._waiting:  # first step of an episode: wait for an arrow key
            self._draw(env, pixels, scene, [*status, "press an arrow key to start"])
            self._pump()
            self._clock.tick(30)
        self._draw(env, pixels, scene, status)
        if self.fps > 0:
            self._clock.tick(self.fps)  # the human reacts to the picture during this wait
        self._pump()
        action = action_from_keys(self.held | self.tapped)
        self.tapped.clear()
        self.executed.append(action)
        return action
