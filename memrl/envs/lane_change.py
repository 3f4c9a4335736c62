"""The lane-change task of the paper as a highway-env environment (``memrl/LaneChange-v0``).

Coordinates follow highway-env: x along the road [m], y across it [m], lane i centred at
y = i * lane_width (lane 0 leftmost in the pictures), heading 0 along +x.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces
from highway_env.envs.common.abstract import AbstractEnv
from highway_env.envs.common.action import ActionType
from highway_env.envs.common.observation import ObservationType
from highway_env.road.lane import LineType, StraightLane
from highway_env.road.road import Road, RoadNetwork

from memrl.envs.config import LaneChangeConfig, env_config_dict, max_car_speed, validate_env_config
from memrl.envs.controllers import CarController, Opponents, make_opponents
from memrl.envs.crash import NO_CRASH, classify
from memrl.envs.render import BEVRenderer, View, car_corners
from memrl.envs.reward import AgentState, components, weighted_sum
from memrl.envs.risk import risk, shaping_reward
from memrl.envs.scene import sample_scene
from memrl.envs.stride import history_length, select_frames
from memrl.envs.vehicles import N_ACTIONS, CurvatureVehicle, validate_action


def _merge(base: dict, delta: dict) -> None:
    """Recursive in-place update that accepts partial nested dicts."""
    # Hand-written: highway-env's utils.update_config requires nested dicts to repeat every key.
    for key, value in delta.items():
        if isinstance(value, dict) and isinstance(base.get(key), dict):
            _merge(base[key], value)
        else:
            base[key] = value


class CurvatureSpeedAction(ActionType):
    """The 9 discrete speed x curvature changes of the paper."""

    def space(self) -> spaces.Discrete:
        return spaces.Discrete(N_ACTIONS)

    @property
    def vehicle_class(self) -> type:
        return CurvatureVehicle

    def act(self, action: Any) -> None:
        self.controlled_vehicle.apply_action(validate_action(action))

    def get_available_actions(self) -> list[int]:
        return list(range(N_ACTIONS))


class BEVObservation(ObservationType):
    """Bird's-eye-view crop centred on the observer car, channel-first uint8 ``[S * C, H, W]``.

    C is 1 (grayscale levels drawn directly, the default) or 3 (RGB), see ``bev.grayscale``;
    S is ``frame_stack`` (frames ``frame_stride`` steps apart, oldest first, the newest the
    current one; after a reset the first frame stands in for earlier steps, as TorchRL's
    ``CatFrames``). ``frame_stack=4`` is the paper's observation.
    """

    def __init__(self, env: LaneChangeEnv) -> None:
        super().__init__(env)
        self.env: LaneChangeEnv = env

    def space(self) -> spaces.Box:
        cfg = self.env.cfg
        channels = (1 if cfg.bev.grayscale else 3) * cfg.frame_stack
        return spaces.Box(0, 255, (channels, cfg.bev.height, cfg.bev.width), np.uint8)

    def observe(self) -> np.ndarray:
        car = self.observer_vehicle
        frame = self.env.observe_from(car, car.target_lane)
        return self.env.stack_frame(frame) if self.env.cfg.frame_stack > 1 else frame


class LaneChangeEnv(AbstractEnv):
    """Change to the target lane among other cars without hitting them or the road edges.

    Reward per step: the sum of the named components of :meth:`_rewards` (each 0 or 1;
    :mod:`memrl.envs.reward`) weighted by ``config['reward'][name]`` (Table II). Terminated on
    collision; truncated after ``duration`` steps. ``info`` holds the components (``rewards``),
    ``collided``, ``on_target_lane`` and ``reached_target`` (all four corners of the agent
    inside the target lane at some step of the episode so far), and of a crash its kind and
    closing speed (``crash_kind``: code of :data:`memrl.envs.crash.CRASH_KINDS`, 0 without a crash;
    ``closing_speed`` [m/s], 0 without one (not NaN: gymnasium's checker compares infos);
    :func:`memrl.envs.crash.classify`).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, config: dict | None = None, render_mode: str | None = None) -> None:
        self.cfg: LaneChangeConfig = validate_env_config(
            {**env_config_dict(), **(config or {})}, allow=AbstractEnv.default_config())
        self.target_lane = 0
        self.reached_target = False
        self.others: list[CurvatureVehicle] = []
        self.controllers: list[CarController] = []
        self._bev: BEVRenderer | None = None
        self._opponents: Opponents | None = None
        self._scene: BEVRenderer | None = None
        self._components: dict[str, float] | None = None
        self._risk_now: float | None = None  # risk of the current state (env.shaping), lazily
        self._risk_before = 0.0  # of the state before the last step
        self._episode = 0
        self._stack: np.ndarray | None = None
        self._stack_key: tuple[int, int] | None = None
        self._ended: str | None = None  # 'terminated' / 'truncated' once the episode has ended
        self._warned_ended = False
        super().__init__(config, render_mode)

    @classmethod
    def default_config(cls) -> dict:
        config = super().default_config()
        config.update(env_config_dict())
        return config

    def configure(self, config: dict) -> None:
        if config:
            _merge(self.config, dict(config))
        self.cfg = validate_env_config(self.config, allow=AbstractEnv.default_config())
        self.config["offscreen_rendering"] = True
        self._bev = self._scene = None
        self._opponents = None

    def define_spaces(self) -> None:
        """Our own action and observation types (highway-env's factories only know theirs)."""
        self.observation_type = BEVObservation(self)
        self.action_type = CurvatureSpeedAction(self)
        self.observation_space = self.observation_type.space()
        self.action_space = self.action_type.space()

    # ----------------------------------------------------------------------------- scene
    def _reset(self) -> None:
        cfg = self.cfg
        self._components = self._risk_now = None
        self.config["simulation_frequency"] = self.config["policy_frequency"] = 1.0 / cfg.dt
        self._make_road()
        if self._opponents is None:  # built once per env: a learned pool is loaded once
            self._opponents = make_opponents(cfg.opponent)
            for controller in self._opponents.controllers:
                if controller.kind == "learned":
                    controller.check_view(cfg)  # type: ignore[attr-defined]
        scene = sample_scene(cfg, self.np_random, self._opponents.pool_size)
        self._episode += 1
        self.target_lane = scene.target_lane
        agent = self._car_from(scene.agent, "agent")
        agent.target_lane = self.target_lane
        self.vehicle = agent
        self.others = [self._car_from(row, "constant") for row in scene.others]
        self.road.vehicles = [agent, *self.others]
        self.controllers = list(self._opponents.controllers)
        for i, car in enumerate(self.others):
            car.controller = self._opponents.of_kind("learned" if scene.learned[i] else "constant")
            car.kind = car.controller.kind
            car.target_lane, car.policy_index = int(scene.car_target[i]), int(scene.policy[i])
        for controller in self.controllers:
            controller.reset(self, self._cars_of(controller))
        self.reached_target = self._inside_target_lane(*self._lateral_extent(agent))

    def _make_road(self) -> None:
        cfg = self.cfg
        net = RoadNetwork()
        for i in range(cfg.lanes_count):
            lines = (
                LineType.CONTINUOUS_LINE if i == 0 else LineType.STRIPED,
                LineType.CONTINUOUS_LINE if i == cfg.lanes_count - 1 else LineType.NONE,
            )
            y = i * cfg.lane_width
            net.add_lane("0", "1", StraightLane([0.0, y], [cfg.road_length, y],
                                                width=cfg.lane_width, line_types=lines))
        self.road = Road(network=net, np_random=self.np_random, record_history=False)

    def _car(self, position: np.ndarray, speed: float, kind: str) -> CurvatureVehicle:
        cfg = self.cfg
        return CurvatureVehicle(
            self.road, position, 0.0, speed,
            length=cfg.vehicle_length, width=cfg.vehicle_width, kind=kind,
            limits={"speed_step": cfg.speed_step, "curvature_step": cfg.curvature_step,
                    "speed_limits": cfg.speed_limits, "curvature_limit": cfg.curvature_limit},
        )

    def _car_from(self, row: np.ndarray, kind: str) -> CurvatureVehicle:
        """A car from a scene's state row (x, y, heading, speed, curvature)."""
        x, y, heading, speed, curvature = (float(v) for v in row)
        car = self._car(np.array([x, y]), speed, kind)
        car.heading, car.curvature = heading, curvature
        return car

    # --------------------------------------------------------------- hand-made situations
    def add_car(self, x: float, y: float, speed: float, heading: float = 0.0,
                controller: CarController | None = None) -> CurvatureVehicle:
        """Put another car at (x, y) [m] with ``speed`` [m/s], driven by ``controller``
        (default: this episode's first controller). For hand-made scenes and tests."""
        controller = controller or self.controllers[0]
        car = self._car(np.array([x, y], dtype=np.float64), speed, controller.kind)
        car.heading = heading
        car.controller = controller
        self.others.append(car)
        self.road.vehicles.append(car)
        self._risk_now = None
        return car

    def remove_others(self) -> None:
        """Remove every other car from the road."""
        self.road.vehicles = [self.vehicle]
        self.others = []
        self._risk_now = None

    def place_agent(self, x: float, y: float, speed: float, heading: float = 0.0,
                    curvature: float = 0.0) -> None:
        """Move the agent to (x, y) [m] with the given state; recomputes ``reached_target``."""
        car = self.vehicle
        car.position = np.array([x, y], dtype=np.float64)
        car.heading, car.speed, car.curvature = heading, speed, curvature
        car.crashed = False
        car.on_state_update()
        self._components = self._risk_now = None
        self.reached_target = self._inside_target_lane(*self._lateral_extent(car))

    def _cars_of(self, controller: CarController) -> list[CurvatureVehicle]:
        return [car for car in self.others if car.controller is controller]

    # ------------------------------------------------------------------------------ step
    def reset(self, *args: Any, **kwargs: Any) -> tuple[np.ndarray, dict]:
        self._ended, self._warned_ended = None, False
        return super().reset(*args, **kwargs)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        """One action step (highway-env's), refusing ``None`` (highway-env would move the other
        cars and not the agent) and warning once when the episode has already ended, as
        gymnasium's own envs and its ``PassiveEnvChecker`` do."""
        validate_action(action)  # None and every other non-action: refused, nothing moves
        if self._ended is not None and not self._warned_ended:
            from gymnasium import logger

            logger.warn(f"step() called after this episode returned {self._ended} = True; "
                        "call reset() before stepping again (what follows is undefined)")
            self._warned_ended = True
        obs, reward, terminated, truncated, info = super().step(action)
        if self._ended is None and (terminated or truncated):
            self._ended = "terminated" if terminated else "truncated"
        return obs, reward, terminated, truncated, info

    def _simulate(self, action: Any = None) -> None:
        """One action step: every car takes its action, then all move by ``dt``."""
        self._risk_before = self.state_risk() if self.cfg.shaping.weight > 0 else 0.0
        self._components = self._risk_now = None
        if action is not None:
            action = validate_action(action)
        # Every car chooses before any car's action applies (the batched engine's order): a
        # learned car's view shows the other cars' speeds and curvatures (``bev.path_time``)
        # as they were when the step began.
        chosen = [(cars, controller.act(self, cars)) for controller in self.controllers
                  if (cars := self._cars_of(controller))]
        if action is not None:
            self.action_type.act(action)
        for cars, actions in chosen:
            for car, a in zip(cars, actions, strict=True):
                car.apply_action(int(a))
        self._move_and_collide(self.cfg.dt)
        self.steps += 1
        lo, hi = self._lateral_extent(self.vehicle)
        if self._hits_wall(lo, hi):
            self.vehicle.crashed = True
        if self._inside_target_lane(lo, hi):
            self.reached_target = True

    def _move_and_collide(self, dt: float) -> None:
        """``Road.step`` with a vectorised distance pre-check before highway-env's polygon test."""
        cars = self.road.vehicles
        for car in cars:
            car.step(dt)
        pos = np.array([c.position for c in cars])
        reach = np.array([c.diagonal for c in cars])
        dist = np.linalg.norm(pos[:, None, :] - pos[None, :, :], axis=-1)
        close = np.triu(dist <= 0.5 * (reach[:, None] + reach[None, :]), k=1)
        for i, j in zip(*np.nonzero(close), strict=True):
            cars[i].handle_collisions(cars[j], 0.0)

    def _lateral_extent(self, car: CurvatureVehicle) -> tuple[float, float]:
        corners_y = car_corners([car])[0, :, 1]
        return float(corners_y.min()), float(corners_y.max())

    def _hits_wall(self, lo: float, hi: float) -> bool:
        """Whether a car spanning [lo, hi] across the road [m] touches a road edge."""
        # Hand-written: highway-env has no wall object for a road edge; any corner beyond it hits.
        w = self.cfg.lane_width
        return lo < -0.5 * w or hi > (self.cfg.lanes_count - 0.5) * w

    def _inside_target_lane(self, lo: float, hi: float) -> bool:
        """Whether a car spanning [lo, hi] across the road [m] lies wholly in the target lane."""
        y = self.target_lane * self.cfg.lane_width
        return y - 0.5 * self.cfg.lane_width <= lo and hi <= y + 0.5 * self.cfg.lane_width

    def current_lane(self, car: CurvatureVehicle | None = None) -> int:
        """Lane holding the car's centre (clipped to the road)."""
        return int((car or self.vehicle).lane_index[2])

    def _rewards(self, action: Any = None) -> dict[str, float]:
        # Computed once per state: step() asks for them twice (reward, then info).
        if self._components is None:
            self._components = self._reward_components()
        return self._components

    def _reward_components(self) -> dict[str, float]:
        """The components of :mod:`memrl.envs.reward` of the current state, as 0.0 / 1.0."""
        car = self.vehicle
        state = AgentState(crashed=car.crashed, y=car.position[1], speed=car.speed,
                           lane=self.current_lane(), target_lane=self.target_lane)
        return {name: float(value) for name, value in components(state, self.cfg).items()}

    def _reward(self, action: Any = None) -> float:
        shaping = self.cfg.shaping
        reward = float(weighted_sum(self._rewards(action), self.cfg.reward))
        if shaping.weight > 0:
            reward += float(shaping_reward(self._risk_before, self.state_risk(), self.vehicle.crashed,
                                           shaping.weight, shaping.gamma))
        return reward

    def state_risk(self) -> float:
        """Collision risk of the current state in [0, 1] (:func:`memrl.envs.risk.risk`)."""
        if self._risk_now is None:
            cfg = self.cfg
            rows = np.array([[c.position[0], c.position[1], c.heading, c.speed, c.curvature]
                             for c in (self.vehicle, *self.others)], dtype=np.float64)
            self._risk_now = float(risk(rows, np.ones(len(rows), dtype=bool), cfg.lane_width,
                                        cfg.lanes_count, cfg.vehicle_length, cfg.vehicle_width,
                                        cfg.shaping.horizon))
        return self._risk_now

    def _is_terminated(self) -> bool:
        return bool(self.vehicle.crashed)

    def _is_truncated(self) -> bool:
        return self.steps >= self.cfg.duration

    def _info(self, obs: Any, action: Any = None) -> dict:
        car, lane = self.vehicle, self.current_lane()
        return {
            "speed": float(car.speed),
            "curvature": float(car.curvature),
            "lane": lane,
            "target_lane": self.target_lane,
            "rewards": self._rewards(action),
            # numpy scalars: TorchRL's info reader needs a dtype on every value
            "collided": np.bool_(car.crashed),
            "on_target_lane": np.bool_(lane == self.target_lane),
            "reached_target": np.bool_(self.reached_target),
            **self._crash_info(),
        }

    def _crash_info(self) -> dict:
        """``crash_kind`` and ``closing_speed`` of the current state (see :mod:`memrl.envs.crash`)."""
        kind, closing = NO_CRASH, 0.0
        if self.vehicle.crashed:
            rows = [[c.position[0], c.position[1], c.heading, c.speed, c.curvature]
                    for c in (self.vehicle, *self.others)]
            cfg = self.cfg
            kind, closing = classify(np.array(rows[0]), np.array(rows[1:]).reshape(-1, 5), cfg.lane_width,
                                     cfg.lanes_count, cfg.vehicle_length, cfg.vehicle_width)
        return {"crash_kind": np.int64(kind), "closing_speed": np.float64(closing)}

    # ------------------------------------------------------------------------- rendering
    @property
    def bev(self) -> BEVRenderer:
        """The observation renderer (the same for the agent and any other car)."""
        if self._bev is None:
            b = self.cfg.bev
            self._bev = BEVRenderer(
                View(b.width, b.height, b.lateral_scale, b.longitudinal_scale),
                self.cfg.lanes_count, self.cfg.lane_width, (self.cfg.vehicle_length, self.cfg.vehicle_width),
                show_target_lane=b.show_target_lane, dash_length=b.dash_length,
                path_length=b.path_length, path_time=b.path_time, max_speed=max_car_speed(self.cfg),
                max_curvature=self.cfg.curvature_limit,
                channels=1 if b.grayscale else 3,
            )
        return self._bev

    def observe_from(self, car: CurvatureVehicle, target_lane: int | None) -> np.ndarray:
        """The ``[C, H, W]`` uint8 view centred on ``car`` with ``target_lane`` highlighted.

        The car itself is drawn in the agent's shade (see :meth:`BEVRenderer.render`), so a
        car driven by a copy of the agent sees the scene as the agent does.
        """
        img = self.bev.render(car.position, self.road.vehicles, target_lane, ego=car)
        return img[None] if img.ndim == 2 else np.ascontiguousarray(img.transpose(2, 0, 1))

    def stack_frame(self, frame: np.ndarray) -> np.ndarray:
        """``frame_stack`` frames ``frame_stride`` steps apart with ``frame`` the newest (pushed
        once per step; see :mod:`memrl.envs.stride`)."""
        key = (self._episode, self.steps)
        if self._stack is None or self._stack_key is None or key[0] != self._stack_key[0]:
            size = history_length(self.cfg.frame_stack, self.cfg.frame_stride)
            self._stack = np.concatenate([frame] * size)  # a new episode: the kept history
        elif key != self._stack_key:
            self._stack = np.concatenate([self._stack[frame.shape[0]:], frame])
        self._stack_key = key
        return select_frames(self._stack, frame.shape[0], self.cfg.frame_stride)

    def render(self) -> np.ndarray | None:
        """Full-scene RGB picture ``(H, W, 3)`` centred on the agent (``render_mode='rgb_array'``)."""
        if self.render_mode != "rgb_array":
            return None
        if self._scene is None:
            s = self.cfg.scene
            self._scene = BEVRenderer(
                View(s.width, s.height, s.lateral_scale, s.longitudinal_scale),
                self.cfg.lanes_count, self.cfg.lane_width, (self.cfg.vehicle_length, self.cfg.vehicle_width),
                show_target_lane=True, dash_length=self.cfg.bev.dash_length,
            )
        return self._scene.render(
            self.vehicle.position, self.road.vehicles, self.target_lane, ego=self.vehicle
        )

    def close(self) -> None:
        self._bev = self._scene = None
        super().close()
