"""The lane-change task for N envs at once, as torch tensors on one device.

The same task as the highway-env reference env (:class:`memrl.envs.lane_change.LaneChangeEnv`),
step for step: the same scenes from the same seeds (one scene sampler,
:func:`memrl.envs.scene.sample_scene`), the same kinematics, collision test, reward components,
termination and frames (one rasterizer, :class:`memrl.envs.render.BEVRenderer`);
``tests/test_batched.py`` proves it. What changes is the cost: one step moves, collides,
rewards and renders every env in a handful of tensor operations.

Car slots: ``[N, C]`` with C = 1 + the most other cars a scene can hold; slot 0 is the agent,
then the scene's other cars in its order (the reference env's ``road.vehicles`` order, which
is also the draw order); empty slots are flagged absent. World state is float64.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from gymnasium.utils.seeding import np_random

from memrl.envs.batched_state import engine_state, load_engine_state
from memrl.envs.config import LaneChangeConfig, env_config_dict, validate_env_config
from memrl.envs.controllers import Opponents, make_opponents
from memrl.envs.render import LABEL, BEVRenderer, View, body_corners
from memrl.envs.scene import max_cars, sample_scene
from memrl.envs.vehicles import ACTIONS, IDLE, N_ACTIONS
from memrl.errors import UserError

X, Y, HEADING, SPEED, CURVATURE = range(5)
REWARD_NAMES = ("collision", "lane_centre", "stopped", "target_lane", "non_target_lane")
NUMPY_MAX_VIEWS = 256
"""On CPU, calls with at most this many views are drawn by the rasterizer's numpy path."""
INFO_KEYS = ("collided", "on_target_lane", "reached_target")
"""Per-step flags of the agent (the reference env's ``info`` keys of the same names)."""


class BatchedEnvError(UserError, ValueError):
    """A bad argument of the batched engine (N, device, action batch)."""


def resolve_device(device: torch.device | str | None) -> torch.device:
    """``auto`` / None: CUDA when present, else CPU; anything else must name an available device."""
    if device is None or str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as err:
        raise BatchedEnvError(f"device {device!r} is not a torch device (auto, cpu, cuda or cuda:K)") from err
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise BatchedEnvError(f"device {device!r}: CUDA is not available on this machine "
                                  "(use device=cpu)")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise BatchedEnvError(f"device {device!r}: only {torch.cuda.device_count()} CUDA device(s) here")
    elif dev.type != "cpu":
        raise BatchedEnvError(f"device {device!r}: expected auto, cpu, cuda or cuda:K")
    return dev


def check_actions(action: Any, n: int, device: torch.device) -> torch.Tensor:
    """The action batch as int64 ``[n]`` on ``device``; one clear error for anything else."""
    t = action if isinstance(action, torch.Tensor) else torch.as_tensor(np.asarray(action))
    if t.dtype == torch.bool or t.dtype.is_floating_point or t.dtype.is_complex:
        raise BatchedEnvError(f"actions must be integers in 0..{N_ACTIONS - 1}, got dtype {t.dtype}")
    if t.shape != (n,):
        raise BatchedEnvError(f"actions must have shape ({n},) (one per env), got {tuple(t.shape)}")
    t = t.to(device=device, dtype=torch.int64)
    if bool(((t < 0) | (t >= N_ACTIONS)).any()):
        bad = t[(t < 0) | (t >= N_ACTIONS)][0].item()
        raise BatchedEnvError(f"action {bad} is outside the valid range 0..{N_ACTIONS - 1}")
    return t


@dataclass
class StepOut:
    """What one step gives, per env (all ``[N]`` on the engine's device)."""

    reward: torch.Tensor
    """float64 reward (Table II components weighted by the config)."""
    components: torch.Tensor
    """``[N, 5]`` bool reward components, in the order of :data:`REWARD_NAMES`."""
    terminated: torch.Tensor
    truncated: torch.Tensor
    collided: torch.Tensor
    on_target_lane: torch.Tensor
    reached_target: torch.Tensor


class BatchedLaneChange:
    """N lane-change envs stepped together on one device.

    Args:
        config: env config values (as for ``gym.make("memrl/LaneChange-v0", config=...)``).
        num_envs: N >= 1.
        device: ``auto``, ``cpu``, ``cuda`` or ``cuda:K``.
        frame_stack: frames per observation stack (oldest first; the first frame repeated
            after a reset, as TorchRL's ``CatFrames``).
        opponents: the other cars' controllers (default: built from ``config['opponent']``;
            pass the reference env's to share a learned pool).
    """

    def __init__(
        self,
        config: Mapping[str, Any] | LaneChangeConfig | None = None,
        num_envs: int = 1,
        device: torch.device | str | None = "cpu",
        frame_stack: int = 4,
        opponents: Opponents | None = None,
    ) -> None:
        if isinstance(num_envs, bool) or not isinstance(num_envs, int | np.integer) or num_envs < 1:
            raise BatchedEnvError(f"num_envs must be an int >= 1, got {num_envs!r}")
        if not isinstance(frame_stack, int) or frame_stack < 1:
            raise BatchedEnvError(f"frame_stack must be an int >= 1, got {frame_stack!r}")
        cfg = config if isinstance(config, LaneChangeConfig) else validate_env_config(
            {**env_config_dict(), **dict(config or {})})
        if not cfg.bev.grayscale:
            raise BatchedEnvError("env.bev.grayscale=false (RGB pictures) is for the reference env only; "
                                  "the batched engine draws grayscale frames")
        self.cfg, self.num_envs, self.frame_stack = cfg, int(num_envs), frame_stack
        self.device = resolve_device(device)
        self.opponents = opponents or make_opponents(cfg.opponent)
        self.learned = next((c for c in self.opponents.controllers if c.kind == "learned"), None)
        if self.learned is not None and self.learned.device != self.device:  # type: ignore[attr-defined]
            self.learned.to(self.device)  # type: ignore[attr-defined]
        n, c, dev = self.num_envs, 1 + max_cars(cfg), self.device
        f64 = torch.float64
        self.state = torch.zeros(n, c, 5, dtype=f64, device=dev)
        """``[N, C, (x, y, heading, speed, curvature)]`` of every car slot."""
        self.present = torch.zeros(n, c, dtype=torch.bool, device=dev)
        self.is_learned = torch.zeros(n, c, dtype=torch.bool, device=dev)
        self.car_target = torch.full((n, c), -1, dtype=torch.long, device=dev)
        self.policy = torch.zeros(n, c, dtype=torch.long, device=dev)
        self.target_lane = torch.zeros(n, dtype=torch.long, device=dev)
        self.steps = torch.zeros(n, dtype=torch.long, device=dev)
        self.crashed = torch.zeros(n, dtype=torch.bool, device=dev)
        self.reached = torch.zeros(n, dtype=torch.bool, device=dev)
        self.rngs: list[np.random.Generator | None] = [None] * n
        b = cfg.bev
        self.renderer = BEVRenderer(
            View(b.width, b.height, b.lateral_scale, b.longitudinal_scale), cfg.lanes_count,
            cfg.lane_width, (cfg.vehicle_length, cfg.vehicle_width), show_target_lane=b.show_target_lane,
            dash_length=b.dash_length, path_length=b.path_length, channels=1, device=dev)
        # frame ring [S, N, H, W] in one flat buffer with a spare last byte (the renderer's)
        self._ring = torch.zeros(frame_stack * n * b.height * b.width + 1, dtype=torch.uint8, device=dev)
        self._frames = self._ring[:-1].view(frame_stack, n, b.height, b.width)
        self._ring_np = self._ring.numpy() if dev.type == "cpu" else None  # the same memory
        self._head = 0  # slot of the newest frame in the ring
        self._car_frames: torch.Tensor | None = None
        self._car_fresh = torch.zeros(n, c, dtype=torch.bool, device=dev)
        if self.learned is not None:
            self._car_frames = torch.zeros(n, c, frame_stack, b.height, b.width, dtype=torch.uint8,
                                           device=dev)
        self._ds = torch.tensor([a[0] for a in ACTIONS], dtype=f64, device=dev) * cfg.speed_step
        self._dk = torch.tensor([a[1] for a in ACTIONS], dtype=f64, device=dev) * cfg.curvature_step
        self._weights = [float(getattr(cfg.reward, k)) for k in REWARD_NAMES]
        self._diag = float(np.sqrt(cfg.vehicle_length ** 2 + cfg.vehicle_width ** 2))

    # ---------------------------------------------------------------------------- reset
    def reset(self, env_ids: Sequence[int] | torch.Tensor | None = None,
              seeds: Sequence[int | None] | None = None) -> None:
        """Start new episodes in ``env_ids`` (None: all), each from its own generator: reseeded
        with ``seeds[i]`` when given (the scene of ``gym reset(seed=s)``), else continued."""
        ids = list(range(self.num_envs)) if env_ids is None else [int(i) for i in
                                                                  torch.as_tensor(env_ids).reshape(-1).tolist()]
        if not ids:
            return
        if seeds is not None and len(seeds) != len(ids):
            raise BatchedEnvError(f"{len(seeds)} seeds for {len(ids)} envs")
        c = self.present.shape[1]
        state = np.zeros((len(ids), c, 5))
        present = np.zeros((len(ids), c), dtype=bool)
        learned = np.zeros((len(ids), c), dtype=bool)
        car_target = np.full((len(ids), c), -1, dtype=np.int64)
        policy = np.zeros((len(ids), c), dtype=np.int64)
        target = np.zeros(len(ids), dtype=np.int64)
        pool = self.opponents.pool_size
        for row, i in enumerate(ids):
            seed = None if seeds is None else seeds[row]
            if seed is not None:
                self.rngs[i] = np_random(int(seed))[0]
            elif self.rngs[i] is None:
                self.rngs[i] = np_random()[0]
            scene = sample_scene(self.cfg, self.rngs[i], pool)  # type: ignore[arg-type]
            k = len(scene.others)
            target[row] = scene.target_lane
            state[row, 0], state[row, 1:1 + k] = scene.agent, scene.others
            present[row, :1 + k] = True
            learned[row, 1:1 + k] = scene.learned
            car_target[row, 0], car_target[row, 1:1 + k] = scene.target_lane, scene.car_target
            policy[row, 1:1 + k] = scene.policy
        idx = torch.tensor(ids, device=self.device)
        dev = self.device
        self.state[idx] = torch.as_tensor(state, dtype=torch.float64, device=dev)
        self.present[idx] = torch.as_tensor(present, device=dev)
        self.is_learned[idx] = torch.as_tensor(learned, device=dev)
        self.car_target[idx] = torch.as_tensor(car_target, device=dev)
        self.policy[idx] = torch.as_tensor(policy, device=dev)
        self.target_lane[idx] = torch.as_tensor(target, device=dev)
        self.steps[idx] = 0
        self.crashed[idx] = False
        lo, hi = self._lateral_extent(self.state[idx, 0])
        self.reached[idx] = self._inside_target(lo, hi, self.target_lane[idx])
        self._frames[:, idx] = self._render_agents(idx)[None]
        self._car_fresh[idx] = True

    # ----------------------------------------------------------------------------- step
    def step(self, actions: Any, active: torch.Tensor | None = None) -> StepOut:
        """One action step of every env (call :meth:`reset` on finished ones before the next).

        ``active`` (bool ``[N]``, default all): envs whose outcome counts; the others are about
        to be reset, and their learned cars draw no exploration from the env's generator (as a
        reference env that is reset instead of stepped).
        """
        a = check_actions(actions, self.num_envs, self.device)
        # Learned cars look before anyone moves; a view shows positions and headings (and the
        # viewer's own path), which the actions below do not change yet: all cars act at once.
        if self._car_frames is not None and bool(self.is_learned.any()):
            car_actions = self._learned_actions(active)
        else:
            car_actions = torch.full(self.present.shape, IDLE, dtype=torch.long, device=self.device)
        car_actions[:, 0] = a
        self._apply(car_actions)
        self._move()
        self.steps += 1
        self.crashed |= self._agent_collides()
        lo, hi = self._lateral_extent(self.state[:, 0])
        w = self.cfg.lane_width
        self.crashed |= (lo < -0.5 * w) | (hi > (self.cfg.lanes_count - 0.5) * w)
        self.reached |= self._inside_target(lo, hi, self.target_lane)
        self._head = (self._head + 1) % self.frame_stack
        self._render_agents(None, into=self._head)
        comps, on_target = self._components()
        reward = torch.zeros(self.num_envs, dtype=torch.float64, device=self.device)
        for i, weight in enumerate(self._weights):  # the reference's order of summation
            reward = reward + weight * comps[:, i].to(torch.float64)
        return StepOut(reward, comps, self.crashed.clone(), self.steps >= self.cfg.duration,
                       self.crashed.clone(), on_target, self.reached.clone())

    def state_dict(self) -> dict[str, Any]:
        """Everything that determines the engine's future (copies; tensors on its device): car
        states, flags, targets, policies, steps, the frame ring, learned cars' frame stacks and
        every env's generator state. ``torch.save`` it to checkpoint mid-episode."""
        return engine_state(self)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue exactly from ``state`` (of :meth:`state_dict`), moved to this engine's device;
        the engine must have the same config, N and frame stack (else :class:`BatchedEnvError`)."""
        load_engine_state(self, state)

    def info(self) -> dict[str, torch.Tensor]:
        """The reference env's ``info`` of the current state, per env: speed [m/s], curvature
        [rad/m], lane, target_lane, rewards (``[N, 5]`` components), collided, on_target_lane,
        reached_target."""
        comps, on_target = self._components()
        agent = self.state[:, 0]
        return {"speed": agent[:, SPEED], "curvature": agent[:, CURVATURE], "lane": self._lane().long(),
                "target_lane": self.target_lane, "rewards": comps, "collided": self.crashed.clone(),
                "on_target_lane": on_target, "reached_target": self.reached.clone()}

    def observation(self) -> torch.Tensor:
        """The stacked frames ``[N, frame_stack, H, W]`` uint8, oldest first (a new tensor)."""
        order = [(self._head + k) % self.frame_stack for k in range(1, self.frame_stack + 1)]
        return torch.stack([self._frames[k] for k in order], dim=1)

    def newest_frame(self) -> torch.Tensor:
        """The last frame of every env ``[N, H, W]`` (a view of the ring)."""
        return self._frames[self._head]

    def _apply(self, actions: torch.Tensor) -> None:
        """Add the speed and curvature changes of the actions ``[N, C]`` to every car, clamp, round."""
        cfg, s = self.cfg, self.state
        low, high = cfg.speed_limits
        speed = torch.clamp(s[..., SPEED] + self._ds[actions], float(low), float(high))
        curv = torch.clamp(s[..., CURVATURE] + self._dk[actions], -cfg.curvature_limit, cfg.curvature_limit)
        # round away float drift, as the reference does with round(x, 9)
        s[..., SPEED] = torch.round(speed, decimals=9)
        s[..., CURVATURE] = torch.round(curv, decimals=9)

    def _move(self) -> None:
        """Every car drives one ``dt`` along its exact arc (straight below a 1e-9 rad turn)."""
        s = self.state
        h, k = s[..., HEADING], s[..., CURVATURE]
        distance = s[..., SPEED] * self.cfg.dt
        turn = k * distance
        straight = turn.abs() < 1e-9
        radius = 1.0 / torch.where(straight, torch.ones_like(k), k)
        new_h = h + turn
        sin_h, cos_h = torch.sin(h), torch.cos(h)
        dx = torch.where(straight, distance * cos_h, radius * (torch.sin(new_h) - sin_h))
        dy = torch.where(straight, distance * sin_h, radius * (cos_h - torch.cos(new_h)))
        s[..., X] += dx
        s[..., Y] += dy
        s[..., HEADING] = torch.where(straight, h, new_h)

    def _corners(self, cars: torch.Tensor) -> torch.Tensor:
        """Body corners ``[..., 4, (x, y)]`` of cars ``[..., 5]`` (the reference env's formula)."""
        return body_corners(cars[..., X], cars[..., Y], cars[..., HEADING], self.cfg.vehicle_length,
                            self.cfg.vehicle_width)

    def _lateral_extent(self, agent: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        y = self._corners(agent)[..., 1]
        return y.min(-1).values, y.max(-1).values

    def _inside_target(self, lo: torch.Tensor, hi: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        w = self.cfg.lane_width
        y = target.to(torch.float64) * w
        return (y - 0.5 * w <= lo) & (hi <= y + 0.5 * w)

    def _agent_collides(self) -> torch.Tensor:
        """Agent against every other car: highway-env's separating-axis test on the bodies,
        after its distance pre-check (``utils.are_polygons_intersecting`` at zero velocity)."""
        agent, others = self.state[:, :1], self.state[:, 1:]
        if others.shape[1] == 0:
            return torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)
        close = torch.linalg.vector_norm(others[..., :2] - agent[..., :2], dim=-1) <= self._diag
        close &= self.present[:, 1:]
        hit = torch.zeros_like(close)
        if self.device.type == "cpu":  # the separating-axis test on the close pairs only
            env_i, car_i = torch.nonzero(close, as_tuple=True)
            hit[env_i, car_i] = self._overlap(agent[env_i, 0], others[env_i, car_i])
        else:  # every pair: fixed shapes, no host sync
            hit = close & self._overlap(agent.expand_as(others), others)
        return hit.any(-1)

    def _overlap(self, first: torch.Tensor, second: torch.Tensor) -> torch.Tensor:
        """Whether car bodies ``[..., 5]`` overlap: highway-env's ``are_polygons_intersecting``
        at zero velocity (the 4 edge normals of each body; touching counts)."""
        a, b = self._corners(first), self._corners(second)  # [..., 4, 2]
        edges = torch.cat([a.roll(-1, dims=-2) - a, b.roll(-1, dims=-2) - b], dim=-2)  # [..., 8, 2]
        nx, ny = -edges[..., 1], edges[..., 0]
        norm = torch.sqrt(nx * nx + ny * ny)
        nx, ny = (nx / norm)[..., None], (ny / norm)[..., None]  # [..., 8 axes, 1]
        pa = a[..., None, :, 0] * nx + a[..., None, :, 1] * ny  # [..., 8 axes, 4 corners]
        pb = b[..., None, :, 0] * nx + b[..., None, :, 1] * ny
        min_a, max_a = pa.min(-1).values, pa.max(-1).values
        min_b, max_b = pb.min(-1).values, pb.max(-1).values
        gap = torch.where(min_a < min_b, min_b - max_a, min_a - max_b)
        return (gap <= 0).all(-1)

    def _lane(self) -> torch.Tensor:
        """Lane holding the agent's centre (clipped to the road), as float64."""
        w = self.cfg.lane_width
        return torch.clamp(torch.floor(self.state[:, 0, Y] / w + 0.5), 0, self.cfg.lanes_count - 1)

    def _components(self) -> tuple[torch.Tensor, torch.Tensor]:
        cfg, agent = self.cfg, self.state[:, 0]
        lane = self._lane()
        offset = agent[:, Y] - lane * cfg.lane_width
        on_target = lane.long() == self.target_lane
        comps = torch.stack([self.crashed, offset.abs() <= cfg.lane_centre_tolerance,
                             agent[:, SPEED] <= cfg.stopped_speed, on_target, ~on_target], dim=-1)
        return comps, on_target

    # --------------------------------------------------------------------------- frames
    def _render_agents(self, idx: torch.Tensor | None, into: int | None = None) -> torch.Tensor:
        """The agent's view of envs ``idx`` (None: all) ``[V, H, W]``; ``into``: draw all envs'
        views straight into that slot of the frame ring."""
        state = self.state if idx is None else self.state[idx]
        present = self.present if idx is None else self.present[idx]
        target = self.target_lane if idx is None else self.target_lane[idx]
        learned = self.is_learned if idx is None else self.is_learned[idx]
        labels = torch.where(learned, LABEL["learned"], LABEL["constant"])
        labels[:, 0] = LABEL["agent"]
        labels = torch.where(present, labels, -1)
        path = state[:, 0, [X, Y, HEADING, CURVATURE]]
        views = (state[:, 0, :2], target, state[..., :3], labels, path)
        if into is not None:
            flat = self._ring_np if self._on_numpy(len(state)) else self._ring
            self.renderer.render_into(flat, into * self._frames[0].numel(), *self._as_backend(views))
            return self._frames[into]
        return self._draw(views)

    def _on_numpy(self, n_views: int) -> bool:
        """Draw these views with numpy: on CPU, up to a few hundred views numpy's lower cost
        per call wins (same code, same pixels; ``python -m memrl.bench batched`` times it)."""
        return self._ring_np is not None and n_views <= NUMPY_MAX_VIEWS

    def _as_backend(self, views: tuple[torch.Tensor, ...]) -> tuple[Any, ...]:
        return tuple(v.numpy() for v in views) if self._on_numpy(len(views[0])) else views

    def _draw(self, views: tuple[torch.Tensor, ...]) -> torch.Tensor:
        """Pictures ``[V, H, W]`` of the views (center, target, cars, labels, path) as a tensor."""
        img = self.renderer.render_batch(*self._as_backend(views))
        return torch.from_numpy(img) if isinstance(img, np.ndarray) else img

    def _learned_actions(self, active: torch.Tensor | None) -> torch.Tensor:
        """Actions ``[N, C]`` of the learned cars (others: IDLE) from their own views, through
        one batched forward pass of the pool; envs not ``active`` draw no exploration."""
        assert self.learned is not None and self._car_frames is not None
        env_i, slot_i = torch.nonzero(self.is_learned, as_tuple=True)
        state = self.state[env_i]  # [M, C, 5] each learned car's env
        labels = torch.where(self.is_learned[env_i], LABEL["learned"], LABEL["constant"])
        labels[:, 0] = LABEL["learned"]  # to a learned car the agent is another learned driver
        labels[torch.arange(len(env_i), device=self.device), slot_i] = LABEL["agent"]
        labels = torch.where(self.present[env_i], labels, -1)
        me = state[torch.arange(len(env_i), device=self.device), slot_i]  # [M, 5]
        frames = self._draw((me[:, :2], self.car_target[env_i, slot_i], state[..., :3], labels,
                             me[:, [X, Y, HEADING, CURVATURE]]))
        stacks = self._car_frames[env_i, slot_i]  # [M, S, H, W]
        fresh = self._car_fresh[env_i, slot_i]
        stacks = torch.where(fresh[:, None, None, None], frames[:, None].expand_as(stacks),
                             torch.cat([stacks[:, 1:], frames[:, None]], dim=1))
        self._car_frames[env_i, slot_i] = stacks
        self._car_fresh[env_i, slot_i] = False
        q = self.learned.q_values(self.policy[env_i, slot_i], stacks)  # type: ignore[attr-defined]
        chosen = q.argmax(-1)
        eps = float(getattr(self.learned, "epsilon", 0.0))
        if eps > 0:  # per env, from the env's generator, in slot order, as the reference does
            chosen_np = chosen.cpu().numpy()
            envs = env_i.cpu().numpy()
            counts = None if active is None else active.cpu().numpy()
            for e in np.unique(envs):
                if counts is not None and not counts[e]:
                    continue
                rows = np.flatnonzero(envs == e)
                rng = self.rngs[int(e)]
                explore = rng.random(len(rows)) < eps  # type: ignore[union-attr]
                chosen_np[rows] = np.where(explore, rng.integers(N_ACTIONS, size=len(rows)),  # type: ignore[union-attr]
                                           chosen_np[rows])
            chosen = torch.as_tensor(chosen_np, device=self.device)
        out = torch.full(self.present.shape, IDLE, dtype=torch.long, device=self.device)
        out[env_i, slot_i] = chosen
        return out
