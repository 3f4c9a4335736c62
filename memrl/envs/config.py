"""Typed configuration of the lane-change environment.

One dataclass is the single source of truth: the env's ``default_config`` is built from it,
Hydra's ConfigStore registers it as the schema of the ``env`` group (so a typo in a key fails
at start), and :func:`validate_env_config` checks values and names the bad key.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from memrl.errors import UserError


@dataclass
class BEVConfig:
    """Bird's-eye-view crop seen by the agent (and by learned cars)."""

    width: int = 84
    """Crop width [px]; the lateral (across-road) axis."""
    height: int = 84
    """Crop height [px]; the longitudinal axis, driving direction pointing up."""
    lateral_scale: float = 0.2
    """Metres per pixel across the road [m/px]: 84 px = 16.8 m, a 2-lane road (8 m) plus margins."""
    longitudinal_scale: float = 0.8
    """Metres per pixel along the road [m/px]: 84 px = 67.2 m, i.e. 33.6 m ahead and behind."""
    show_target_lane: bool = True
    """Paint the target lane in its own shade: the only cue the agent has of where to go."""
    dash_length: float = 3.0
    """Length of a painted lane-marking dash [m] (gaps have the same length)."""
    path_length: float = 0.0
    """Draw the viewing car's path for this many metres ahead at its current heading and
    curvature, a 1-px line in its own shade (0: off, the paper's picture). The curvature is
    otherwise hard to see: one 0.01 rad/m step turns the car by under a pixel's worth over
    four frames, and the scripted prior knowledge steers by it
    (``python -m memrl.bench stage1`` compares)."""
    grayscale: bool = True
    """Draw each shade's grayscale level directly (observation ``[1, H, W]``); exactly TorchRL's
    ``GrayScale`` of the RGB drawing, 3x less work. False: RGB ``[3, H, W]`` observations, and
    the TorchRL pipeline converts them with ``GrayScale``."""


@dataclass
class SceneRenderConfig:
    """Full-scene picture returned by ``render()`` (``render_mode='rgb_array'``), for people."""

    width: int = 120
    """Picture width [px] (across the road): 24 m at 0.2 m/px."""
    height: int = 500
    """Picture height [px] (along the road, driving direction up): 100 m at 0.2 m/px."""
    lateral_scale: float = 0.2
    """Metres per pixel across the road [m/px]."""
    longitudinal_scale: float = 0.2
    """Metres per pixel along the road [m/px]."""


@dataclass
class RewardConfig:
    """Weights of the named reward components (Table II); each component is 0 or 1 per step."""

    collision: float = -5.0
    """Collision with another car or with the road edge (wall)."""
    lane_centre: float = 1.0
    """Agent's centre within ``lane_centre_tolerance`` of a lane centre line."""
    stopped: float = -1.0
    """Agent's speed at or below ``stopped_speed``."""
    target_lane: float = 1.0
    """Agent's centre in the target lane."""
    non_target_lane: float = -2.0
    """Agent's centre in any other lane."""


@dataclass
class OpponentConfig:
    """Who drives the other cars (Sec. IV-A: constant speed, or a copy of an earlier agent)."""

    type: str = "constant"
    """constant: straight at constant speed | learned: every car driven by a past agent |
    mixed: each car learned with probability ``learned_fraction``, else constant."""
    learned_fraction: float = 0.5
    """mixed: probability that a car is driven by a past agent."""
    pool: list[str] = field(default_factory=list)
    """Past agents: run folders, ``final.pt`` files or glob patterns; each learned car draws
    one per episode. Needed by learned and mixed."""
    epsilon: float = 0.0
    """Learned cars act epsilon-greedily with this epsilon (0: greedy)."""


@dataclass
class LaneChangeConfig:
    """Lane-change task of the paper (Sec. IV-A) on a straight multi-lane road."""

    lanes_count: int = 2
    """Number of lanes; lane 0 is the leftmost."""
    lane_width: float = 4.0
    """Lane width [m]. Road edges (walls) lie half a lane outside the outer lane centres."""
    road_length: float = 5000.0
    """Length of the straight road [m]; the agent starts 500 m from its beginning."""
    vehicle_length: float = 5.0
    """Length of every car [m]."""
    vehicle_width: float = 2.0
    """Width of every car [m]."""
    dt: float = 0.1
    """Duration of one action step [s]; one kinematic integration per step."""
    duration: int = 300
    """Episode length [action steps]; the episode is truncated after this many steps."""
    speed_step: float = 0.1
    """Speed change of the 'faster'/'slower' actions [m/s]."""
    curvature_step: float = 0.01
    """Curvature change of the 'left'/'right' actions [rad/m]."""
    speed_limits: list[float] = field(default_factory=lambda: [0.0, 15.0])
    """Clamp of the agent's speed [m/s] (min, max)."""
    curvature_limit: float = 0.05
    """Clamp of |curvature| [rad/m]; 0.05 rad/m is a 20 m turning radius."""
    initial_speed: list[float] = field(default_factory=lambda: [6.0, 9.0])
    """Agent's initial speed drawn uniformly in this range [m/s]."""
    initial_offset: float = 0.0
    """Agent's initial lateral offset from its lane centre, uniform in [-x, x] [m] (0: on the
    centre line). With ``initial_heading`` and ``initial_curvature``, off-nominal starts that
    make a recorded driver show how it recovers (prior knowledge); off by default."""
    initial_heading: float = 0.0
    """Agent's initial heading, uniform in [-x, x] [rad] (0: along the road)."""
    initial_curvature: float = 0.0
    """Agent's initial curvature, uniform in [-x, x] [rad/m] (0: straight)."""
    target_lane: Any = "random"
    """Target lane index, or 'random' (uniform over lanes, drawn each episode)."""
    initial_lane: str = "random"
    """'random': start in the target or a non-target lane with equal probability;
    'non_goal': always start in a non-target lane."""
    vehicles_count: Any = 5
    """Number of other cars: an int, or [low, high] drawn uniformly (inclusive) each episode."""
    other_speed: list[float] = field(default_factory=lambda: [5.0, 9.0])
    """Speeds of other cars drawn uniformly in this range [m/s]."""
    spawn_ahead: float = 60.0
    """Other cars spawn at most this far ahead of the agent [m]."""
    spawn_behind: float = 30.0
    """Other cars spawn at most this far behind the agent [m]."""
    spawn_gap: float = 8.0
    """Minimum centre-to-centre gap between two cars of one lane at spawn, beyond one car
    length [m]; a car in the agent's lane keeps twice this gap from the agent."""
    spawn_attempts: int = 50
    """Rejection-sampling attempts per car; a car that finds no room is left out."""
    opponent: OpponentConfig = field(default_factory=OpponentConfig)
    """Who drives the other cars (a plain string is read as ``opponent.type``)."""
    lane_centre_tolerance: float = 0.3
    """|lateral offset| from a lane centre line at which the agent counts as centred [m]."""
    stopped_speed: float = 0.05
    """Speed at or below which the agent counts as stopped [m/s]."""
    reward: RewardConfig = field(default_factory=RewardConfig)
    """Weights of the named reward components."""
    bev: BEVConfig = field(default_factory=BEVConfig)
    """The agent's bird's-eye-view observation."""
    scene: SceneRenderConfig = field(default_factory=SceneRenderConfig)
    """The full-scene picture for people (preview, videos)."""
    frame_stack: int = 1
    """Frames in the gym observation ``[frame_stack, H, W]`` (oldest first; after a reset the
    first frame repeated): 4 is the paper's observation, for gym users (SB3, CleanRL). The
    TorchRL pipeline (``make_env``) stacks frames itself and leaves this at 1."""
    frame_stride: int = 1
    """Steps between stacked frames, k: the stack at step t (0 at reset) holds the frames of
    steps t - (S-1)k, ..., t - k, t (S frames, oldest first), the reset frame standing in for
    steps before 0, as Atari's frame skip spaces its frames while the agent still acts every
    step here. 1: consecutive frames, the paper's observation. Every engine uses it: the gym
    stack (``frame_stack``), the TorchRL pipeline, the batched engine, the evaluation and
    deploy runners and the learned cars' own views (see :mod:`memrl.envs.stride`)."""
    num_envs: int = 1
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


def _check_range(cfg: LaneChangeConfig, key: str, low_min: float = 0.0) -> None:
    value = getattr(cfg, key)
    _check(
        isinstance(value, list | tuple) and len(value) == 2 and low_min <= value[0] <= value[1],
        key,
        f"expected [low, high] with {low_min} <= low <= high, got {value!r}",
    )


def validate_env_config(values: dict[str, Any], allow: Iterable[str] = ()) -> LaneChangeConfig:
    """Build a :class:`LaneChangeConfig` from a (possibly partial) dict and check every value.

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
    _check(isinstance(cfg.lanes_count, int) and cfg.lanes_count >= 2, "lanes_count", "need >= 2")
    for key in ("lane_width", "vehicle_length", "vehicle_width", "dt", "road_length"):
        _check(getattr(cfg, key) > 0, key, f"must be > 0, got {getattr(cfg, key)!r}")
    _check(cfg.vehicle_width < cfg.lane_width, "vehicle_width", "must be < lane_width")
    _check(isinstance(cfg.duration, int) and cfg.duration >= 1, "duration", "need an int >= 1")
    for key in ("speed_limits", "initial_speed", "other_speed"):
        _check_range(cfg, key)
    _check(cfg.curvature_limit > 0, "curvature_limit", "must be > 0")
    _check(0 <= cfg.initial_offset < 0.5 * (cfg.lane_width - cfg.vehicle_width), "initial_offset",
           "need 0 <= initial_offset < (lane_width - vehicle_width) / 2")
    _check(0 <= cfg.initial_heading < 0.5, "initial_heading", "need 0 <= initial_heading < 0.5 rad")
    _check(0 <= cfg.initial_curvature <= cfg.curvature_limit, "initial_curvature",
           "need 0 <= initial_curvature <= curvature_limit")
    target = cfg.target_lane
    _check(
        target == "random" or (isinstance(target, int) and 0 <= target < cfg.lanes_count),
        "target_lane",
        f"expected 'random' or an int in [0, {cfg.lanes_count - 1}], got {target!r}",
    )
    _check(
        cfg.initial_lane in ("random", "non_goal"),
        "initial_lane",
        f"expected 'random' or 'non_goal', got {cfg.initial_lane!r}",
    )
    count = cfg.vehicles_count
    if isinstance(count, list | tuple):
        _check(
            len(count) == 2 and all(isinstance(c, int) for c in count) and 0 <= count[0] <= count[1],
            "vehicles_count",
            f"expected [low, high] ints with 0 <= low <= high, got {count!r}",
        )
    else:
        _check(isinstance(count, int) and count >= 0, "vehicles_count", f"need an int >= 0, got {count!r}")
    _check(cfg.spawn_ahead >= 0 and cfg.spawn_behind >= 0, "spawn_ahead", "spawn ranges must be >= 0")
    _check(cfg.lane_centre_tolerance >= 0, "lane_centre_tolerance", "must be >= 0")
    opp = cfg.opponent
    _check(opp.type in ("constant", "learned", "mixed"), "opponent.type",
           f"expected constant, learned or mixed, got {opp.type!r}")
    _check(0.0 <= opp.learned_fraction <= 1.0, "opponent.learned_fraction", "must be in [0, 1]")
    _check(0.0 <= opp.epsilon <= 1.0, "opponent.epsilon", "must be in [0, 1]")
    _check(opp.type == "constant" or len(opp.pool) > 0, "opponent.pool",
           f"opponent.type={opp.type} needs a pool of past agents (run folders or final.pt files)")
    for name in ("bev", "scene"):
        sub = getattr(cfg, name)
        for key in ("width", "height"):
            _check(getattr(sub, key) >= 8, f"{name}.{key}", "must be >= 8 px")
        for key in ("lateral_scale", "longitudinal_scale"):
            _check(getattr(sub, key) > 0, f"{name}.{key}", "must be > 0 m/px")
    _check(cfg.bev.path_length >= 0, "bev.path_length", "must be >= 0 m (0: no path drawn)")
    stack = cfg.frame_stack
    _check(isinstance(stack, int) and not isinstance(stack, bool) and stack >= 1,
           "frame_stack", f"need an int >= 1, got {cfg.frame_stack!r}")
    stride = cfg.frame_stride
    _check(isinstance(stride, int) and not isinstance(stride, bool) and stride >= 1,
           "frame_stride", f"need an int >= 1, got {cfg.frame_stride!r}")
    n = cfg.num_envs
    _check(isinstance(n, int) and not isinstance(n, bool) and n >= 1,
           "num_envs", f"need an int >= 1, got {cfg.num_envs!r}")
    return cfg


def env_config_dict(cfg: LaneChangeConfig | None = None) -> dict[str, Any]:
    """The plain nested dict of a config (defaults when ``cfg`` is None)."""
    return dataclasses.asdict(cfg or LaneChangeConfig())
