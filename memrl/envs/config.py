"""Typed configuration of the lane-change environment.

One dataclass is the single source of truth: the env's ``default_config`` is built from it,
Hydra's ConfigStore registers it as the schema of the ``env`` group (so a typo in a key fails
at start), and :func:`validate_env_config` checks values and names the bad key.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from memrl.errors import ConfigError, UserError
from memrl.fields import check_fields, spec


@dataclass
class BEVConfig:
    """Bird's-eye-view crop seen by the agent (and by learned cars)."""

    width: int = spec(84, ge=8)
    """Crop width [px]; the lateral (across-road) axis."""
    height: int = spec(84, ge=8)
    """Crop height [px]; the longitudinal axis, driving direction pointing up."""
    lateral_scale: float = spec(0.2, gt=0)
    """Metres per pixel across the road [m/px]: 84 px = 16.8 m, a 2-lane road (8 m) plus margins."""
    longitudinal_scale: float = spec(0.8, gt=0)
    """Metres per pixel along the road [m/px]: 84 px = 67.2 m, i.e. 33.6 m ahead and behind."""
    show_target_lane: bool = True
    """Paint the target lane in its own shade: the only cue the agent has of where to go."""
    dash_length: float = spec(3.0, gt=0)
    """Length of a painted lane-marking dash [m] (gaps have the same length)."""
    path_length: float = spec(0.0, ge=0)
    """Draw the viewing car's path for this many metres ahead at its current heading and
    curvature, a 1-px line in its own shade (0: off, the paper's picture). The curvature is
    otherwise hard to see: one 0.01 rad/m step turns the car by under a pixel's worth over
    four frames, and the scripted prior knowledge steers by it
    (``python -m memrl.bench stage1`` compares)."""
    path_time: float = spec(0.0, ge=0, le=10)
    """Draw EVERY car's path ahead of it at its current heading and curvature for this many
    seconds of driving, ``speed * path_time`` metres, a 1-px line in that car's shade under the
    cars (0: off; at most 10 s; not together with ``path_length``). Its length shows each car's
    speed, which the frames otherwise hide: at 0.8 m/px along the road and 0.1 s between
    frames, a car closing on the one ahead at under 0.8 / 0.3 = 2.7 m/s moves less than a
    pixel across a 4-frame stack, yet a 1 m/s closing speed lengthens or shortens the gap
    between the two lines' tips by ``path_time / 0.8`` px per m/s (2.5 px at 2 s). At constant
    speeds the tips are where the cars will be after ``path_time`` seconds: the own line's tip
    reaching the tip of the car ahead means a rear-end within ``path_time``."""
    grayscale: bool = True
    """Draw each shade's grayscale level directly (observation ``[1, H, W]``); exactly TorchRL's
    ``GrayScale`` of the RGB drawing, 3x less work. False: RGB ``[3, H, W]`` observations, and
    the TorchRL pipeline converts them with ``GrayScale``."""


@dataclass
class SceneRenderConfig:
    """Full-scene picture returned by ``render()`` (``render_mode='rgb_array'``), for people."""

    width: int = spec(120, ge=8)
    """Picture width [px] (across the road): 24 m at 0.2 m/px."""
    height: int = spec(500, ge=8)
    """Picture height [px] (along the road, driving direction up): 100 m at 0.2 m/px."""
    lateral_scale: float = spec(0.2, gt=0)
    """Metres per pixel across the road [m/px]."""
    longitudinal_scale: float = spec(0.2, gt=0)
    """Metres per pixel along the road [m/px]."""


@dataclass
class RewardConfig:
    """Weights of the named reward components (Table II); each component is 0 or 1 per step."""

    collision: float = spec(-5.0, finite=True)
    """Collision with another car or with the road edge (wall)."""
    lane_centre: float = spec(1.0, finite=True)
    """Agent's centre within ``lane_centre_tolerance`` of a lane centre line."""
    stopped: float = spec(-1.0, finite=True)
    """Agent's speed at or below ``stopped_speed``."""
    target_lane: float = spec(1.0, finite=True)
    """Agent's centre in the target lane."""
    non_target_lane: float = spec(-2.0, finite=True)
    """Agent's centre in any other lane."""


@dataclass
class ShapingConfig:
    """Potential-based shaping of the reward by collision risk (:mod:`memrl.envs.risk`): every
    step's reward gains ``weight (risk(s) - gamma risk(s'))`` (0 after a crash), which leaves
    the task's optimal policy unchanged. Off by default; the paper's reward is Table II's."""

    weight: float = spec(0.0, ge=0)
    """Weight of the potential ``Phi = -weight risk`` (0: no shaping)."""
    horizon: float = spec(3.0, gt=0)
    """Time to collision [s] at which the risk is 0; it grows linearly to 1 at contact."""
    gamma: float = spec(0.95, gt=0, le=1)
    """Discount of the shaping; must equal the learner's ``agent.gamma`` (checked at the
    start of training), or the optimal policy is no longer the task's."""


@dataclass
class OpponentConfig:
    """Who drives the other cars (Sec. IV-A: constant speed, or a copy of an earlier agent)."""

    type: str = spec("constant", choices=("constant", "learned", "mixed"))
    """constant: straight at constant speed | learned: every car driven by a past agent |
    mixed: each car learned with probability ``learned_fraction``, else constant."""
    learned_fraction: float = spec(0.5, ge=0, le=1)
    """mixed: probability that a car is driven by a past agent."""
    pool: list[str] = field(default_factory=list)
    """Past agents: run folders, ``final.pt`` files or glob patterns; each learned car draws
    one per episode. Needed by learned and mixed."""
    epsilon: float = spec(0.0, ge=0, le=1)
    """Learned cars act epsilon-greedily with this epsilon (0: greedy)."""


@dataclass
class LaneChangeConfig:
    """Lane-change task of the paper (Sec. IV-A) on a straight multi-lane road."""

    lanes_count: int = spec(2, ge=2)
    """Number of lanes; lane 0 is the leftmost."""
    lane_width: float = spec(4.0, gt=0)
    """Lane width [m]. Road edges (walls) lie half a lane outside the outer lane centres."""
    road_length: float = spec(5000.0, gt=0)
    """Length of the straight road [m]; the agent starts 500 m from its beginning."""
    vehicle_length: float = spec(5.0, gt=0)
    """Length of every car [m]."""
    vehicle_width: float = spec(2.0, gt=0)
    """Width of every car [m]."""
    dt: float = spec(0.1, gt=0)
    """Duration of one action step [s]; one kinematic integration per step."""
    duration: int = spec(300, ge=1)
    """Episode length [action steps]; the episode is truncated after this many steps."""
    speed_step: float = spec(0.1, ge=0)
    """Speed change of the 'faster'/'slower' actions [m/s]."""
    curvature_step: float = spec(0.01, ge=0)
    """Curvature change of the 'left'/'right' actions [rad/m]."""
    speed_limits: list[float] = spec([0.0, 15.0], ge=0)
    """Clamp of the agent's speed [m/s] (min, max)."""
    curvature_limit: float = spec(0.05, gt=0)
    """Clamp of |curvature| [rad/m]; 0.05 rad/m is a 20 m turning radius."""
    initial_speed: list[float] = spec([6.0, 9.0], ge=0)
    """Agent's initial speed drawn uniformly in this range [m/s]."""
    initial_offset: float = spec(0.0, ge=0)
    """Agent's initial lateral offset from its lane centre, uniform in [-x, x] [m] (0: on the
    centre line). With ``initial_heading`` and ``initial_curvature``, off-nominal starts that
    make a recorded driver show how it recovers (prior knowledge); off by default."""
    initial_heading: float = spec(0.0, ge=0)
    """Agent's initial heading, uniform in [-x, x] [rad] (0: along the road)."""
    initial_curvature: float = spec(0.0, ge=0)
    """Agent's initial curvature, uniform in [-x, x] [rad/m] (0: straight)."""
    target_lane: Any = "random"
    """Target lane index, or 'random' (uniform over lanes, drawn each episode)."""
    initial_lane: str = spec("random", choices=("random", "non_goal"))
    """'random': start in the target or a non-target lane with equal probability;
    'non_goal': always start in a non-target lane."""
    vehicles_count: Any = 5
    """Number of other cars: an int, or [low, high] drawn uniformly (inclusive) each episode."""
    other_speed: list[float] = spec([5.0, 9.0], ge=0)
    """Speeds of other cars drawn uniformly in this range [m/s]."""
    spawn_ahead: float = spec(60.0, ge=0)
    """Other cars spawn at most this far ahead of the agent [m]."""
    spawn_behind: float = spec(30.0, ge=0)
    """Other cars spawn at most this far behind the agent [m]."""
    spawn_gap: float = spec(8.0, ge=0)
    """Minimum centre-to-centre gap between two cars of one lane at spawn, beyond one car
    length [m]; a car in the agent's lane keeps twice this gap from the agent."""
    spawn_attempts: int = spec(50, ge=1)
    """Rejection-sampling attempts per car; a car that finds no room is left out."""
    opponent: OpponentConfig = field(default_factory=OpponentConfig)
    """Who drives the other cars (a plain string is read as ``opponent.type``)."""
    lane_centre_tolerance: float = spec(0.3, ge=0)
    """|lateral offset| from a lane centre line at which the agent counts as centred [m]."""
    stopped_speed: float = spec(0.05, ge=0)
    """Speed at or below which the agent counts as stopped [m/s]."""
    reward: RewardConfig = field(default_factory=RewardConfig)
    """Weights of the named reward components."""
    shaping: ShapingConfig = field(default_factory=ShapingConfig)
    """Potential-based shaping by collision risk (off by default)."""
    bev: BEVConfig = field(default_factory=BEVConfig)
    """The agent's bird's-eye-view observation."""
    scene: SceneRenderConfig = field(default_factory=SceneRenderConfig)
    """The full-scene picture for people (preview, videos)."""
    frame_stack: int = spec(1, ge=1)
    """Frames in the gym observation ``[frame_stack, H, W]`` (oldest first; after a reset the
    first frame repeated): 4 is the paper's observation, for gym users (SB3, CleanRL). The
    TorchRL pipeline (``make_env``) stacks frames itself and leaves this at 1."""
    frame_stride: int = spec(1, ge=1)
    """Steps between stacked frames, k: the stack at step t (0 at reset) holds the frames of
    steps t - (S-1)k, ..., t - k, t (S frames, oldest first), the reset frame standing in for
    steps before 0, as Atari's frame skip spaces its frames while the agent still acts every
    step here. 1: consecutive frames, the paper's observation. Every engine uses it: the gym
    stack (``frame_stack``), the TorchRL pipeline, the batched engine, the evaluation and
    deploy runners and the learned cars' own views (see :mod:`memrl.envs.stride`)."""
    num_envs: int = spec(1, ge=1)
    """Envs the trainer steps together: 1 steps this highway-env env (the reference); N > 1
    the batched engine (:mod:`memrl.envs.batched`, the same task). A gym env is one env
    whatever this says (``gymnasium.make_vec`` takes ``num_envs`` itself)."""


class BatchedEnvError(UserError, ValueError):
    """A bad argument of the batched engine (N, device, action batch)."""


class EnvConfigError(UserError, ValueError):
    """A lane-change env config value is missing, unknown or out of range."""


def _check(ok: bool, key: str, message: str) -> None:
    if not ok:
        raise EnvConfigError(f"env config '{key}': {message}")


def _build(cls: type, values: dict[str, Any], prefix: str) -> Any:
    names = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(names))
    _check(not unknown, prefix + ",".join(unknown), f"unknown key(s); known: {sorted(names)}")
    kwargs = {}
    for name, value in values.items():
        sub = names[name].default_factory  # type: ignore[misc]
        if sub is OpponentConfig and isinstance(value, str):
            value = {"type": value}  # shorthand: opponent=mixed
        if dataclasses.is_dataclass(sub) and isinstance(value, dict):
            value = _build(sub, value, f"{prefix}{name}.")  # type: ignore[arg-type]
        kwargs[name] = value
    return cls(**kwargs)


AGENT_X = 500.0
"""Where the agent starts along the road [m] (``memrl.envs.scene`` places the scene there)."""


def max_cars_room(cfg: LaneChangeConfig) -> int:
    """Other cars that always find room at spawn, however the earlier ones were placed.

    Spawn keeps centres ``vehicle_length + spawn_gap`` apart (``d``) within a window of
    ``spawn_behind + spawn_ahead`` per lane, and clear of the agent by ``vehicle_length +
    2 spawn_gap``. When no room is left, the open intervals of half-width ``d`` round the placed
    cars (and the agent's) cover the window, so a lane full to the brim holds at least
    ``ceil((window - agent's share) / 2d)`` cars: beyond that total a car may find no room.
    """
    d = cfg.vehicle_length + cfg.spawn_gap
    low, high = AGENT_X - cfg.spawn_behind, AGENT_X + cfg.spawn_ahead
    agent_gap = cfg.vehicle_length + 2 * cfg.spawn_gap
    window = high - low
    agent_share = max(0.0, min(AGENT_X + agent_gap, high) - max(AGENT_X - agent_gap, low))
    others = math.ceil(window / (2 * d)) if window > 0 else 1
    own = max(0, math.ceil((window - agent_share) / (2 * d))) if window > 0 else 0
    return (cfg.lanes_count - 1) * others + own


def min_spawn_gap(cfg: LaneChangeConfig) -> float:
    """The smallest ``spawn_gap`` with no overlap at spawn [m]: cars of one lane are straight,
    so 0 (bumper to bumper); the agent may start turned by up to ``initial_heading``, which
    lengthens its footprint along the road to ``L cos h + W sin h`` and needs
    ``2 spawn_gap >= (L cos h + W sin h - L) / 2``."""
    h = cfg.initial_heading
    along = cfg.vehicle_length * math.cos(h) + cfg.vehicle_width * math.sin(h)
    return max(0.0, (along - cfg.vehicle_length) / 4)


def min_road_length(cfg: LaneChangeConfig) -> float:
    """The road an episode can use [m]: from 0 to the farthest a car can get in ``duration``
    steps (the agent starts at 500 m, other cars up to ``spawn_ahead`` beyond it)."""
    t = cfg.duration * cfg.dt
    return AGENT_X + max(cfg.speed_limits[1] * t, cfg.spawn_ahead + cfg.other_speed[1] * t) \
        + cfg.vehicle_length


def max_car_speed(cfg: LaneChangeConfig) -> float:
    """The highest speed any car can have [m/s]: the agent's and learned cars' clamp, or the
    fastest constant-speed car (the longest ``bev.path_time`` path is this times path_time)."""
    return max(cfg.speed_limits[1], cfg.other_speed[1])


def _pair(value: Any) -> bool:
    """A ``[low, high]`` range (each value's own range is its field's)."""
    return isinstance(value, list | tuple) and len(value) == 2 and value[0] <= value[1]


def _int_ok(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def _check_together(cfg: LaneChangeConfig) -> None:
    """Checks across keys: ranges that must fit together (each key's own range was checked)."""
    _check(_pair(cfg.speed_limits), "speed_limits",
           f"expected [low, high] with low <= high, got {cfg.speed_limits!r}")
    _check(_pair(cfg.initial_speed), "initial_speed",
           f"expected [low, high] with low <= high, got {cfg.initial_speed!r}")
    _check(_pair(cfg.other_speed), "other_speed",
           f"expected [low, high] with low <= high, got {cfg.other_speed!r}")
    _check(cfg.vehicle_width < cfg.lane_width, "vehicle_width", "must be < lane_width")
    _check(cfg.bev.path_length == 0 or cfg.bev.path_time == 0, "bev.path_length,bev.path_time",
           f"two path cues ({cfg.bev.path_length} m of the own path, {cfg.bev.path_time} s of every "
           "car's): set one of them to 0")
    low, high = cfg.speed_limits
    _check(low <= cfg.initial_speed[0] and cfg.initial_speed[1] <= high, "initial_speed",
           f"{list(cfg.initial_speed)} must lie inside speed_limits {list(cfg.speed_limits)}")
    _check(cfg.initial_offset < 0.5 * (cfg.lane_width - cfg.vehicle_width), "initial_offset",
           "need 0 <= initial_offset < (lane_width - vehicle_width) / 2")
    _check(cfg.initial_heading < 0.5, "initial_heading", "need 0 <= initial_heading < 0.5 rad")
    _check(cfg.initial_curvature <= cfg.curvature_limit, "initial_curvature",
           "need 0 <= initial_curvature <= curvature_limit")
    gap = min_spawn_gap(cfg)
    _check(cfg.spawn_gap >= gap, "spawn_gap",
           f"{cfg.spawn_gap} lets cars overlap at spawn; need >= {gap:.3g} m")
    road = min_road_length(cfg)
    _check(cfg.road_length >= road, "road_length",
           f"{cfg.road_length} m is shorter than an episode can drive (the agent starts at "
           f"{AGENT_X:g} m); need >= {road:.0f} m")
    target = cfg.target_lane
    _check(target == "random" or (isinstance(target, int) and not isinstance(target, bool)
                                  and 0 <= target < cfg.lanes_count),
           "target_lane", f"expected 'random' or an int in [0, {cfg.lanes_count - 1}], got {target!r}")
    count = cfg.vehicles_count
    if isinstance(count, list | tuple):
        _check(len(count) == 2 and all(_int_ok(c) for c in count) and count[0] <= count[1],
               "vehicles_count", f"expected [low, high] ints with 0 <= low <= high, got {count!r}")
    else:
        _check(_int_ok(count), "vehicles_count", f"need an int >= 0, got {count!r}")
    most = max(count) if isinstance(count, list | tuple) else count
    room = max_cars_room(cfg)
    _check(most <= room, "vehicles_count",
           f"{count!r}: the spawn window holds at most {room} other cars for sure (raise "
           "spawn_ahead / spawn_behind, or lower spawn_gap)")
    opp = cfg.opponent
    _check(opp.type == "constant" or len(opp.pool) > 0, "opponent.pool",
           f"opponent.type={opp.type} needs a pool of past agents (run folders or final.pt files)")


def validate_env_config(values: dict[str, Any], allow: Iterable[str] = ()) -> LaneChangeConfig:
    """Build a :class:`LaneChangeConfig` from a (possibly partial) dict and check every value:
    each key alone (the range on its field, :func:`memrl.fields.spec`: finite numbers in range),
    then the keys together (:func:`_check_together`).

    Args:
        values: keys of :class:`LaneChangeConfig`.
        allow: other keys to accept and ignore (highway-env's own config keys).

    Returns:
        The typed, checked config.

    Raises:
        EnvConfigError: naming the first bad key and why.
    """
    allowed = set(allow)
    cfg: LaneChangeConfig = _build(
        LaneChangeConfig, {k: v for k, v in values.items() if k not in allowed}, "")
    try:  # each key's range, declared on its field, as every schema's (memrl.fields)
        check_fields(LaneChangeConfig, dataclasses.asdict(cfg))
    except ConfigError as err:
        raise EnvConfigError(f"env {err}") from None  # "env config '<key>': ..."
    _check_together(cfg)
    return cfg


def env_config_dict(cfg: LaneChangeConfig | None = None) -> dict[str, Any]:
    """The plain nested dict of a config (defaults when ``cfg`` is None)."""
    return dataclasses.asdict(cfg or LaneChangeConfig())
