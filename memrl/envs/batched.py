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

from memrl.envs import batched_physics as physics
from memrl.envs.batched_state import engine_state, load_engine_state
from memrl.envs.config import (
    BatchedEnvError,
    LaneChangeConfig,
    env_config_dict,
    max_car_speed,
    validate_env_config,
)
from memrl.envs.controllers import Opponents, make_opponents
from memrl.envs.crash import NO_CRASH, classify_batch
from memrl.envs.render import LABEL, BEVRenderer, View, body_corners
from memrl.envs.reward import AgentState, components, weighted_sum
from memrl.envs.risk import risk, shaping_reward
from memrl.envs.scene import max_cars, sample_scene
from memrl.envs.stride import history_length
from memrl.envs.vehicles import ACTIONS, IDLE, N_ACTIONS

X, Y, HEADING, SPEED, CURVATURE = range(5)
NUMPY_MAX_VIEWS = 2048
"""On CPU, calls with at most this many views are drawn by the rasterizer's numpy path."""
SCENE_PARTS = ("state", "present", "target_lane", "is_learned", "car_target", "policy", "reached")
"""What a new scene sets, per env (names of the engine's arrays)."""
INFO_KEYS = ("collided", "on_target_lane", "reached_target")
"""Per-step flags of the agent (the reference env's ``info`` keys of the same names)."""


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
    # on CPU, numpy's reductions are cheaper calls; elsewhere one check on the device
    out_of_range = (int(t.numpy().min()) < 0 or int(t.numpy().max()) >= N_ACTIONS) if device.type == "cpu" \
        else bool(((t < 0) | (t >= N_ACTIONS)).any())
    if out_of_range:
        bad = t[(t < 0) | (t >= N_ACTIONS)][0].item()
        raise BatchedEnvError(f"action {bad} is outside the valid range 0..{N_ACTIONS - 1}")
    return t


@dataclass
class StepOut:
    """What one step gives, per env (all ``[N]`` on the engine's device)."""

    reward: torch.Tensor
    """float64 reward (Table II components weighted by the config)."""
    components: dict[str, torch.Tensor]
    """float64 reward components (0.0 / 1.0) by name, in the order of
    :data:`memrl.envs.reward.REWARD_NAMES` (the reference env's ``info['rewards']``)."""
    terminated: torch.Tensor
    truncated: torch.Tensor
    collided: torch.Tensor
    on_target_lane: torch.Tensor
    reached_target: torch.Tensor
    crash_kind: torch.Tensor | None = None
    """int64 crash kind code (:data:`memrl.envs.crash.CRASH_KINDS` index + 1; 0: no crash),
    from the state at the crash (the reference env's ``info['crash_kind']``)."""
    closing_speed: torch.Tensor | None = None
    """float64 closing speed [m/s] of the crash (0 without one; ``info['closing_speed']``)."""
    reset_ids: torch.Tensor | None = None
    """``step(auto_reset=True)``: the envs this step finished and reset (else None)."""
    final_observation: torch.Tensor | None = None
    """``step(auto_reset=True)``: their last observations ``[K, S, H, W]``, before the reset."""


class BatchedLaneChange:
    """N lane-change envs stepped together on one device.

    Args:
        config: env config values (as for ``gym.make("memrl/LaneChange-v0", config=...)``).
        num_envs: N >= 1.
        device: ``auto``, ``cpu``, ``cuda`` or ``cuda:K``.
        frame_stack: frames per observation stack (oldest first, ``config['frame_stride']``
            steps apart; the first frame standing in for steps before a reset, as TorchRL's
            ``CatFrames``; see :mod:`memrl.envs.stride`).
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
        self.frame_stride = cfg.frame_stride
        self.history = history_length(frame_stack, self.frame_stride)
        """Frames kept per env (ring slots): the stack's span, ``(S - 1) * stride + 1``."""
        self.device = resolve_device(device)
        self.opponents = opponents or make_opponents(cfg.opponent)
        self.learned = next((c for c in self.opponents.controllers if c.kind == "learned"), None)
        if self.learned is not None:
            self.learned.check_view(cfg)  # type: ignore[attr-defined]
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
        self.crash_kind = torch.zeros(n, dtype=torch.long, device=dev)
        """Crash kind code per env (0 until the episode's crash; :mod:`memrl.envs.crash`)."""
        self.closing_speed = torch.zeros(n, dtype=f64, device=dev)
        self.rngs: list[np.random.Generator | None] = [None] * n
        b = cfg.bev
        self.renderer = BEVRenderer(
            View(b.width, b.height, b.lateral_scale, b.longitudinal_scale), cfg.lanes_count,
            cfg.lane_width, (cfg.vehicle_length, cfg.vehicle_width), show_target_lane=b.show_target_lane,
            dash_length=b.dash_length, path_length=b.path_length, path_time=b.path_time,
            max_speed=max_car_speed(cfg), max_curvature=cfg.curvature_limit, channels=1, device=dev)
        # frame ring [L, N, H, W] (L = history) in one flat buffer: each slot followed by N
        # scratch pictures (first frames of envs reset in the same render call, see step),
        # then a spare last byte (the renderer's)
        self._slot_size = 2 * n * b.height * b.width
        self._ring = torch.zeros(self.history * self._slot_size + 1, dtype=torch.uint8, device=dev)
        slots = self._ring[:-1].view(self.history, 2 * n, b.height, b.width)
        self._frames, self._scratch = slots[:, :n], slots[:, n:]
        self._ring_np = self._ring.numpy() if dev.type == "cpu" else None  # the same memory
        # on CPU, numpy's fancy indexing copies a few frames many times faster than torch's
        self._frames_np = None if self._ring_np is None else self._frames.numpy()
        self._head = 0  # slot of the newest frame in the ring
        self._car_frames: torch.Tensor | None = None
        self._car_fresh = torch.zeros(n, c, dtype=torch.bool, device=dev)
        if self.learned is not None:
            # each learned car's last L frames, newest last (it sees every stride-th)
            self._car_frames = torch.zeros(n, c, self.history, b.height, b.width, dtype=torch.uint8,
                                           device=dev)
        ds = torch.tensor([a[0] for a in ACTIONS], dtype=f64, device=dev) * cfg.speed_step
        dk = torch.tensor([a[1] for a in ACTIONS], dtype=f64, device=dev) * cfg.curvature_step
        self._tensors: dict[str, Any] = {
            "state": self.state, "crashed": self.crashed, "reached": self.reached, "steps": self.steps,
            "target_lane": self.target_lane, "present": self.present, "is_learned": self.is_learned,
            "car_target": self.car_target, "policy": self.policy, "car_fresh": self._car_fresh,
            "crash_kind": self.crash_kind, "closing_speed": self.closing_speed, "ds": ds, "dk": dk}
        # on CPU the step's many small operations run on numpy views of the same memory
        self._on_cpu = dev.type == "cpu"
        self._arrays = {k: v.numpy() for k, v in self._tensors.items()} if self._on_cpu else self._tensors
        self._diag = float(np.sqrt(cfg.vehicle_length ** 2 + cfg.vehicle_width ** 2))
        self._body = (cfg.vehicle_length, cfg.vehicle_width)

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
        idx, scenes = self._draw_scenes(ids, seeds)
        self._install(idx, scenes)
        self._first_frames(idx, self._draw(self._agent_views(*scenes[:4])))

    def _first_frames(self, idx: torch.Tensor, frames: torch.Tensor) -> None:
        """Fill every slot of the frame stacks of envs ``idx`` with their first frames."""
        if self._frames_np is not None:
            self._frames_np[:, idx.numpy()] = frames.numpy()[None]
        else:
            self._frames[:, idx] = frames[None]

    def _draw_scenes(self, ids: list[int], seeds: Sequence[int | None] | None
                     ) -> tuple[torch.Tensor, tuple[Any, ...]]:
        """New scenes of envs ``ids`` from their generators: the env index tensor and their
        :data:`SCENE_PARTS` (numpy arrays on CPU, else tensors on the engine's device)."""
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
        # reached_target at the start: the reference env's formula on the same numpy rows
        y = body_corners(state[:, 0, X], state[:, 0, Y], state[:, 0, HEADING], self.cfg.vehicle_length,
                         self.cfg.vehicle_width)[..., 1]
        half, centre = 0.5 * self.cfg.lane_width, target * self.cfg.lane_width
        reached = (centre - half <= y.min(-1)) & (y.max(-1) <= centre + half)
        dev = self.device
        parts = (state, present, target, learned, car_target, policy, reached)
        if self._on_cpu:
            return torch.tensor(ids), parts
        return torch.tensor(ids, device=dev), tuple(torch.as_tensor(a, device=dev) for a in parts)

    def _install(self, idx: torch.Tensor, scenes: tuple[Any, ...]) -> None:
        """Envs ``idx`` start the episodes ``scenes`` (of :meth:`_draw_scenes`); frames aside."""
        b, at = self._arrays, idx.numpy() if self._on_cpu else idx
        for name, value in zip(SCENE_PARTS, scenes, strict=True):
            b[name][at] = value
        b["steps"][at] = 0
        b["crashed"][at] = False
        b["crash_kind"][at] = NO_CRASH
        b["closing_speed"][at] = 0.0
        b["car_fresh"][at] = True

    # ----------------------------------------------------------------------------- step
    def step(self, actions: Any, active: torch.Tensor | None = None, auto_reset: bool = False,
             reset: Sequence[int] | None = None) -> StepOut:
        """One action step of every env (call :meth:`reset` on finished ones before the next,
        or pass ``auto_reset``, or ``reset`` them in the next step).

        Args:
            actions: ``[N]`` action indices.
            active: bool ``[N]`` (default all): envs whose outcome counts; the others are about
                to be reset, and their learned cars draw no exploration from the env's
                generator (as a reference env that is reset instead of stepped).
            auto_reset: reset the envs that this step finishes, as :meth:`reset` would right
                after the step (same scenes), drawing their first frames in the same call as
                every env's new frame; the finished episodes' last observations are in
                ``StepOut.final_observation`` (rows ``StepOut.reset_ids``), and
                :meth:`observation` gives the new episodes' first.
            reset: envs (not ``active``) to reset instead, as :meth:`reset` right after the
                step (same scenes; their outcomes in ``StepOut`` are of no episode), their
                first frames drawn in the same call as every other env's new frame (not
                together with ``auto_reset``).
        """
        if reset and auto_reset:
            raise BatchedEnvError("step(): pass auto_reset or reset, not both")
        a = check_actions(actions, self.num_envs, self.device)
        # Learned cars look before anyone moves; a view shows positions and headings (and the
        # viewer's own path), which the actions below do not change yet: all cars act at once.
        if self._car_frames is not None and bool(self.is_learned.any()):
            car_actions = self._learned_actions(active)
        else:
            car_actions = torch.full(self.present.shape, IDLE, dtype=torch.long, device=self.device)
        car_actions[:, 0] = a
        cfg, w, b = self.cfg, self.cfg.lane_width, self._arrays  # numpy views on CPU, else the tensors
        acts = car_actions.numpy() if self._on_cpu else car_actions
        low, high = cfg.speed_limits
        risk_before = self._risk(b) if cfg.shaping.weight > 0 else None
        physics.apply_actions(b["state"], b["ds"][acts], b["dk"][acts], (low, high), cfg.curvature_limit)
        physics.move(b["state"], cfg.dt)
        b["steps"] += 1
        before = b["crashed"].copy() if self._on_cpu else b["crashed"].clone()
        hit, touch = self._agent_collides()
        b["crashed"] |= hit.numpy() if self._on_cpu else hit
        lo, hi = physics.lateral_extent(b["state"][:, 0], cfg.vehicle_length, cfg.vehicle_width)
        b["crashed"] |= (lo < -0.5 * w) | (hi > (cfg.lanes_count - 0.5) * w)
        b["reached"] |= physics.inside_target(lo, hi, b["target_lane"], w)
        self._classify_crashes(b["crashed"] & ~before, touch)
        self._head = (self._head + 1) % self.history
        comps, on_target = self._components(b)
        reward = weighted_sum(comps, cfg.reward)
        if risk_before is not None:
            reward = reward + shaping_reward(risk_before, self._risk(b), b["crashed"], cfg.shaping.weight,
                                             cfg.shaping.gamma)
        crashed, truncated, new = b["crashed"], b["steps"] >= cfg.duration, self._new_tensor
        out = StepOut(reward=new(reward), components=self._as_tensors(comps), terminated=new(crashed),
                      truncated=new(truncated), collided=new(crashed), on_target_lane=new(on_target),
                      reached_target=new(b["reached"]), crash_kind=self.crash_kind.clone(),
                      closing_speed=self.closing_speed.clone())
        if reset:  # new episodes before the frames are drawn: their first frames in the same call
            idx, scenes = self._draw_scenes([int(i) for i in reset], None)
            self._install(idx, scenes)
        views = self._agent_views(b["state"], b["present"], b["target_lane"], b["is_learned"])
        done: list[int] = []
        if auto_reset:
            ended = crashed | truncated  # terminated | truncated
            done = (np.flatnonzero(ended) if self._on_cpu else torch.nonzero(ended).flatten()).tolist()
        if not done:
            self._render_into(self._head, views)
            if reset:
                self._first_frames(idx, self._frames[self._head, idx])
            return out
        # the finished envs' last frames and their new scenes' first frames in one call: the
        # new ones land in the scratch pictures that follow the ring's newest slot
        idx, scenes = self._draw_scenes(done, None)
        first = self._agent_views(*scenes[:4])
        cat = np.concatenate if self._on_cpu else torch.cat
        self._render_into(self._head, tuple(cat([v, f]) for v, f in zip(views, first, strict=True)))
        out.reset_ids = idx
        out.final_observation = self.observation(idx)
        self._install(idx, scenes)
        self._first_frames(idx, self._scratch[self._head, : len(done)])
        return out

    def _risk(self, b: dict[str, Any]) -> Any:
        """Collision risk ``[N]`` of every env's state (:func:`memrl.envs.risk.risk`)."""
        cfg = self.cfg
        return risk(b["state"], b["present"], cfg.lane_width, cfg.lanes_count, cfg.vehicle_length,
                    cfg.vehicle_width, cfg.shaping.horizon)

    def _classify_crashes(self, new: Any, touch: Any) -> None:
        """Kind and closing speed of the crashes of envs ``new`` (bool ``[N]``), this step's
        state (:func:`memrl.envs.crash.classify`, as the reference env's ``info``), given which
        cars touch each agent (``touch [N, C - 1]``, of :meth:`_agent_collides`)."""
        ids = np.flatnonzero(new) if self._on_cpu else torch.nonzero(new).flatten().cpu().numpy()
        if len(ids) == 0:
            return
        cfg, b = self.cfg, self._arrays  # numpy views on CPU
        at = ids if self._on_cpu else torch.as_tensor(ids, device=self.device)
        state, present = b["state"][at], b["present"][at]
        if not self._on_cpu:
            state, present = state.cpu().numpy(), present.cpu().numpy()
        touching = touch[at] if self._on_cpu else touch[at].cpu().numpy()
        kind, closing = classify_batch(state[:, 0], state[:, 1:], present[:, 1:], cfg.lane_width,
                                       cfg.lanes_count, *self._body, touch=touching)
        if self._on_cpu:
            b["crash_kind"][at], b["closing_speed"][at] = kind, closing
        else:
            self.crash_kind[at] = torch.as_tensor(kind, device=self.device)
            self.closing_speed[at] = torch.as_tensor(closing, device=self.device)

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
        [rad/m], lane, target_lane, rewards (the components by name, as ``StepOut.components``),
        collided, on_target_lane, reached_target, crash_kind, closing_speed (of the episode's
        crash, as set at its step; not part of :meth:`state_dict`)."""
        comps, on_target = self._components(self._arrays)  # numpy views on CPU, else the tensors
        agent, cfg = self._arrays["state"][:, 0], self.cfg
        lane = physics.lane(agent, cfg.lane_width, cfg.lanes_count)
        rewards: Any = self._as_tensors(comps)  # (name -> tensor)
        return {"speed": self.state[:, 0, SPEED], "curvature": self.state[:, 0, CURVATURE],
                "lane": torch.from_numpy(lane.astype(np.int64)) if self._on_cpu else lane.long(),
                "target_lane": self.target_lane, "rewards": rewards,
                "collided": self.crashed.clone(), "on_target_lane": self._new_tensor(on_target),
                "reached_target": self.reached.clone(), "crash_kind": self.crash_kind.clone(),
                "closing_speed": self.closing_speed.clone()}

    def _components(self, b: dict[str, Any]) -> tuple[dict[str, Any], Any]:
        """The reward components of the arrays ``b`` (numpy or tensors) by name, as new float64
        arrays (0.0 / 1.0, converted from :func:`memrl.envs.reward.components`' truth values),
        and whether each agent is on its target lane."""
        cfg, agent = self.cfg, b["state"][:, 0]
        state = AgentState(crashed=b["crashed"], y=agent[:, Y], speed=agent[:, SPEED],
                           lane=physics.lane(agent, cfg.lane_width, cfg.lanes_count),
                           target_lane=b["target_lane"])
        truth, f64 = components(state, cfg), physics.ops(agent).f64
        return {name: f64(value) for name, value in truth.items()}, truth["target_lane"]

    def _new_tensor(self, x: Any) -> torch.Tensor:
        """A tensor copy of the step's array ``x`` (numpy on CPU, else a tensor)."""
        return torch.from_numpy(x.copy()) if self._on_cpu else x.clone()

    def _as_tensors(self, comps: dict[str, Any]) -> dict[str, torch.Tensor]:
        """Components of :meth:`_components` as tensors (numpy's without a copy: they are new)."""
        return {name: torch.from_numpy(v) for name, v in comps.items()} if self._on_cpu else comps

    def observation(self, env_ids: torch.Tensor | None = None) -> torch.Tensor:
        """The stacked frames ``[N, frame_stack, H, W]`` uint8, oldest first (a new tensor), of
        every env or of ``env_ids``: the frames of steps t - (S-1)k, ..., t - k, t."""
        s, k = self.frame_stack, self.frame_stride
        order = [(self._head - k * (s - 1 - j)) % self.history for j in range(s)]
        if env_ids is None:
            if self._frames_np is not None:  # numpy's copy is several times cheaper here
                return torch.from_numpy(np.stack([self._frames_np[k] for k in order], axis=1))
            return torch.stack([self._frames[k] for k in order], dim=1)
        if self._frames_np is not None:
            picked = self._frames_np[np.array(order)[:, None], env_ids.numpy()[None, :]]  # [S, K, H, W]
            return torch.from_numpy(np.ascontiguousarray(picked.swapaxes(0, 1)))
        return torch.stack([self._frames[k].index_select(0, env_ids) for k in order], dim=1)

    def newest_frame(self) -> torch.Tensor:
        """The last frame of every env ``[N, H, W]`` (a view of the ring)."""
        return self._frames[self._head]

    def _agent_collides(self) -> tuple[torch.Tensor, Any]:
        """Agent against every other car: highway-env's separating-axis test on the bodies,
        after its distance pre-check (``utils.are_polygons_intersecting`` at zero velocity):
        whether each agent touches a car ``[N]``, and which ``[N, C - 1]`` (numpy on CPU)."""
        agent, others = self.state[:, :1], self.state[:, 1:]
        if others.shape[1] == 0:
            none = torch.zeros(others.shape[:2], dtype=torch.bool, device=self.device)
            return none.any(-1), none.numpy() if self._on_cpu else none
        if self.device.type == "cpu":  # numpy (cheaper calls), the separating-axis test on close pairs
            state, present = self.state.numpy(), self.present.numpy()
            # the reference's own pre-check: np.linalg.norm of the centre offsets
            close = np.linalg.norm(state[:, 1:, :2] - state[:, :1, :2], axis=-1) <= self._diag
            env_i, car_i = np.nonzero(close & present[:, 1:])
            pairs = np.zeros(close.shape, dtype=bool)
            on = physics.overlap(state[env_i, 0], state[env_i, car_i + 1], *self._body)
            pairs[env_i[on], car_i[on]] = True
            return torch.from_numpy(pairs.any(-1)), pairs
        # every pair: fixed shapes, no host sync
        close = torch.linalg.vector_norm(others[..., :2] - agent[..., :2], dim=-1) <= self._diag
        touch = close & self.present[:, 1:] & physics.overlap(agent.expand_as(others), others, *self._body)
        return touch.any(-1), touch

    # --------------------------------------------------------------------------- frames
    def _agent_views(self, state: Any, present: Any, target: Any, learned: Any) -> tuple[Any, ...]:
        """The agents' views (center, target, cars, labels, path) of envs in these states
        (numpy arrays or tensors)."""
        where: Any = np.where if isinstance(state, np.ndarray) else torch.where
        labels = where(learned, LABEL["learned"], LABEL["constant"])
        labels[:, 0] = LABEL["agent"]
        labels = where(present, labels, -1)
        return state[:, 0, :2], target, state[..., :3], labels, self._paths(state, state[:, 0])

    def _paths(self, state: Any, viewer: Any) -> Any:
        """The renderer's ``path`` of views of env states ``[V, C, 5]`` by the cars ``viewer
        [V, 5]``: every car's (x, y, heading, curvature, speed) when ``bev.path_time > 0``, else
        the viewer's (x, y, heading, curvature) (drawn when ``bev.path_length > 0``)."""
        if self.renderer.path_time > 0:
            return state[..., [X, Y, HEADING, CURVATURE, SPEED]]
        return viewer[:, [X, Y, HEADING, CURVATURE]]

    def _render_into(self, slot: int, views: tuple[Any, ...]) -> None:
        """Draw the views into the ring's ``slot`` (N of them), then its scratch pictures."""
        flat = self._ring_np if self._on_numpy(len(views[0])) else self._ring
        self.renderer.render_into(flat, slot * self._slot_size, *self._as_backend(views))

    def _on_numpy(self, n_views: int) -> bool:
        """Draw these views with numpy: on CPU, up to a few hundred views numpy's lower cost
        per call wins (same code, same pixels; ``python -m memrl.bench batched`` times it)."""
        return self._ring_np is not None and n_views <= NUMPY_MAX_VIEWS

    def _as_backend(self, views: tuple[Any, ...]) -> tuple[Any, ...]:
        """The views as numpy arrays for the rasterizer's numpy path, else as tensors."""
        if self._on_numpy(len(views[0])):
            return tuple(v if isinstance(v, np.ndarray) else v.numpy() for v in views)
        return tuple(torch.as_tensor(v, device=self.device) for v in views)

    def _draw(self, views: tuple[Any, ...]) -> torch.Tensor:
        """Pictures ``[V, H, W]`` of the views (center, target, cars, labels, path) as a tensor."""
        img = self.renderer.render_batch(*self._as_backend(views))
        return torch.from_numpy(img) if isinstance(img, np.ndarray) else img

    def _learned_actions(self, active: torch.Tensor | None) -> torch.Tensor:
        """Actions ``[N, C]`` of the learned cars (others: IDLE) from their own views, through
        one call of the pool; the cars of envs not ``active`` (about to be reset, or idle) stay
        IDLE and cost nothing (their views restart at the reset)."""
        assert self.learned is not None and self._car_frames is not None
        out = torch.full(self.present.shape, IDLE, dtype=torch.long, device=self.device)
        driven = self.is_learned if active is None else self.is_learned & active.to(self.device)[:, None]
        if not bool(driven.any()):
            return out
        env_i, slot_i = torch.nonzero(driven, as_tuple=True)
        state = self.state[env_i]  # [M, C, 5] each learned car's env
        labels = torch.where(self.is_learned[env_i], LABEL["learned"], LABEL["constant"])
        labels[:, 0] = LABEL["learned"]  # to a learned car the agent is another learned driver
        labels[torch.arange(len(env_i), device=self.device), slot_i] = LABEL["agent"]
        labels = torch.where(self.present[env_i], labels, -1)
        me = state[torch.arange(len(env_i), device=self.device), slot_i]  # [M, 5]
        frames = self._draw((me[:, :2], self.car_target[env_i, slot_i], state[..., :3], labels,
                             self._paths(state, me)))
        stacks = self._car_frames[env_i, slot_i]  # [M, L, H, W]
        fresh = self._car_fresh[env_i, slot_i]
        stacks = torch.where(fresh[:, None, None, None], frames[:, None].expand_as(stacks),
                             torch.cat([stacks[:, 1:], frames[:, None]], dim=1))
        self._car_frames[env_i, slot_i] = stacks
        self._car_fresh[env_i, slot_i] = False
        seen = stacks if self.frame_stride == 1 else stacks[:, ::self.frame_stride].contiguous()
        q = self.learned.q_values(self.policy[env_i, slot_i], seen)  # type: ignore[attr-defined]
        chosen = q.argmax(-1)
        eps = float(getattr(self.learned, "epsilon", 0.0))
        if eps > 0:  # per env, from the env's generator, in slot order, as the reference does
            chosen_np = chosen.cpu().numpy()
            envs = env_i.cpu().numpy()
            for e in np.unique(envs):
                rows = np.flatnonzero(envs == e)
                rng = self.rngs[int(e)]
                explore = rng.random(len(rows)) < eps  # type: ignore[union-attr]
                chosen_np[rows] = np.where(explore, rng.integers(N_ACTIONS, size=len(rows)),  # type: ignore[union-attr]
                                           chosen_np[rows])
            chosen = torch.as_tensor(chosen_np, device=self.device)
        out[env_i, slot_i] = chosen
        return out
