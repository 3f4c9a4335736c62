"""The evaluation protocol of Table III: fixed scenes, per-episode records and the two scores.

*Survival score*: episodes with no collision during the ``duration`` (300) action steps.
*Goal score*: episodes in which the agent was wholly inside the target lane at some step
within the 300 steps (the env's ``reached_target`` flag; with ``initial_lane=random`` about
half the episodes start there and count from step 0, as in the paper's "random" row).
Both are given per 100 episodes, so they read like the paper's counts out of 100.

Episode ``i`` of every evaluation is reset with :func:`scenario_seed` (base seed, ``i``), so
every policy meets the same scenes; the seeds are written into ``eval.json`` and the CSV.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from omegaconf import DictConfig, OmegaConf

from memrl.errors import UserError
from memrl.fields import SEED_MAX, spec

INITIAL_LANES = ("random", "non_goal")
"""The initial-lane settings of Table III."""

DOMAINS = {"test": 0x7E57, "periodic": 0x9E71, "stage1": 0x5171}
"""Seed domains: the final protocol's scenes, the (different) scenes of periodic evaluation
during training and those of mode B's stage-1 behaviour checks; all differ from the training
episodes' seeds."""


@dataclass
class ProtocolConfig:
    """What is evaluated: the scenes and the episode rules (not how fast it runs)."""

    episodes: int = spec(100, ge=1)
    """Episodes per initial-lane setting (the paper: 100)."""
    seed: int = spec(0, ge=0, le=SEED_MAX)
    """Base of the scenario seeds: episode i is reset with ``scenario_seed(seed, i)``."""
    initial_lanes: list[str] = field(default_factory=lambda: list(INITIAL_LANES))
    """Initial-lane settings to evaluate: ``random`` (target or not, 50/50) and/or ``non_goal``."""
    vehicles_count: list[int] = spec([0, 5], ge=0)
    """Other cars per episode, drawn uniformly in [low, high] (inclusive)."""
    duration: int = spec(300, ge=1)
    """Action steps per episode [steps]; a survivor drives all of them."""
    opponent: Any = "constant"
    """Who drives the other cars: a type name, or the full ``env.opponent`` node (e.g. learned
    traffic from a pool); constant-speed cars in the paper's evaluation."""


class ProtocolError(UserError, ValueError):
    """A protocol value is out of range; the message names the key."""


def check_protocol(cfg: ProtocolConfig | Mapping[str, Any] | DictConfig) -> ProtocolConfig:
    """A typed, checked :class:`ProtocolConfig` from a config node or mapping."""
    from memrl.errors import ConfigError
    from memrl.fields import check_fields

    if isinstance(cfg, DictConfig):
        cfg = OmegaConf.to_container(cfg, resolve=True)  # type: ignore[assignment]
    try:
        check_fields(ProtocolConfig, asdict(cfg) if isinstance(cfg, ProtocolConfig) else cfg, "protocol.")
    except ConfigError as err:
        raise ProtocolError(str(err)) from None
    p = cfg if isinstance(cfg, ProtocolConfig) else ProtocolConfig(**dict(cfg))  # type: ignore[arg-type]
    opponent = dict(p.opponent) if isinstance(p.opponent, Mapping) else {"type": str(p.opponent)}
    if opponent.get("type") == "constant":
        opponent = {"type": "constant"}  # the other keys mean nothing for constant cars
    p = ProtocolConfig(int(p.episodes), int(p.seed), [str(x) for x in p.initial_lanes],
                       [int(x) for x in p.vehicles_count], int(p.duration),
                       opponent["type"] if len(opponent) == 1 else opponent)
    if p.episodes < 1:
        raise ProtocolError(f"protocol 'episodes': need >= 1, got {p.episodes}")
    bad = [x for x in p.initial_lanes if x not in INITIAL_LANES]
    if bad or not p.initial_lanes or len(set(p.initial_lanes)) != len(p.initial_lanes):
        raise ProtocolError(f"protocol 'initial_lanes': expected distinct values of {INITIAL_LANES}, "
                            f"got {p.initial_lanes}")
    if len(p.vehicles_count) != 2 or not 0 <= p.vehicles_count[0] <= p.vehicles_count[1]:
        raise ProtocolError(f"protocol 'vehicles_count': expected [low, high] with 0 <= low <= high, "
                            f"got {p.vehicles_count}")
    if p.duration < 1:
        raise ProtocolError(f"protocol 'duration': need >= 1, got {p.duration}")
    return p


def scenario_seed(base: int, index: int, domain: str = "test") -> int:
    """Reset seed of episode ``index``: fixed by the domain, the base seed and the index."""
    return int(np.random.SeedSequence([DOMAINS[domain], int(base), int(index)]).generate_state(1)[0])


def scenario_seeds(base: int, episodes: int, domain: str = "test") -> list[int]:
    """The reset seeds of episodes ``0 .. episodes-1``."""
    return [scenario_seed(base, i, domain) for i in range(episodes)]


def protocol_env(base_env: Mapping[str, Any] | DictConfig | None, protocol: ProtocolConfig,
                 initial_lane: str) -> dict[str, Any]:
    """The env config of one initial-lane setting: the policy's own env (observation, road,
    rewards) with the protocol's episode rules on top."""
    if isinstance(base_env, DictConfig):
        values: dict[str, Any] = OmegaConf.to_container(base_env, resolve=True)  # type: ignore[assignment]
    else:
        values = json.loads(json.dumps(dict(base_env or {})))  # deep, plain copy
    values.update(initial_lane=initial_lane, vehicles_count=list(protocol.vehicles_count),
                  duration=protocol.duration, opponent=protocol.opponent)
    return values


def protocol_id(protocol: ProtocolConfig) -> str:
    """Short hash of what makes results comparable: the scenes and rules of each setting.

    ``initial_lanes`` is left out: a setting's scenes do not depend on which other settings
    were evaluated (e.g. people who drove only the ``random`` starts, as in the paper)."""
    values = asdict(protocol)
    del values["initial_lanes"]
    text = json.dumps(values, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def traffic_type(opponent: Any) -> str:
    """The opponent type of a protocol's ``opponent`` (a type name or an ``env.opponent`` node)."""
    return str(opponent.get("type", "constant") if isinstance(opponent, Mapping) else opponent)


def traffic_tag(opponent: Any) -> str:
    """A protocol's other cars as a folder suffix: '' for the paper's constant-speed traffic,
    else the opponent type (``mixed``, ``learned``)."""
    kind = traffic_type(opponent)
    return "" if kind == "constant" else kind


def suffixed(name: str, tag: str) -> str:
    """``name`` for constant test traffic, ``name_<tag>`` for other traffic."""
    return f"{name}_{tag}" if tag else name


def eval_subdir(opponent: Any) -> str:
    """A trained run's evaluation folder under test traffic ``opponent``: ``eval`` for the
    paper's constant-speed cars, ``eval_<type>`` (``eval_mixed``) for other traffic; the same
    for ``memrl.evaluate`` and the study."""
    return suffixed("eval", traffic_tag(opponent))


def closing_or_none(kind: int, value: float) -> float | None:
    """A closing speed as an :class:`EpisodeRecord` holds it: None without a crash (kind 0)."""
    return None if int(kind) == 0 else float(value)


@dataclass
class EpisodeRecord:
    """Outcome of one evaluation episode (one row of the per-episode CSV)."""

    initial_lane: str
    """``random`` or ``non_goal``."""
    episode: int
    """Index within the protocol (0 .. episodes-1)."""
    seed: int
    """Reset seed of the scene."""
    steps: int
    """Action steps driven: ``duration`` for a survivor, fewer after a collision."""
    episode_return: float
    """Sum of rewards."""
    collided: bool
    """Hit another car or the road edge."""
    reached_target: bool
    """Wholly inside the target lane at some step (from step 0 on)."""
    duration: int = 300
    """The protocol's episode length [steps]."""
    target_lane: int = -1
    start_lane: int = -1
    vehicles: int = -1
    """Other cars in the scene."""
    crash_kind: str = ""
    """Of a collision: ``ahead``, ``behind``, ``side`` or ``road_edge`` (:mod:`memrl.envs.crash`);
    ``""`` without one."""
    closing_speed: float | None = None
    """Of a collision: closing speed [m/s] (:mod:`memrl.envs.crash`); None without one."""

    @property
    def survived(self) -> bool:
        """No collision during all ``duration`` steps."""
        return not self.collided and self.steps >= self.duration

    @property
    def goal(self) -> bool:
        """Reached the target lane within the episode."""
        return bool(self.reached_target)

    @property
    def started_on_target(self) -> bool:
        return self.start_lane == self.target_lane and self.start_lane >= 0

    def row(self) -> dict[str, Any]:
        """CSV row: the fields, plus the derived ``survived``, ``goal``, ``started_on_target``."""
        values = asdict(self)
        values["return"] = round(values.pop("episode_return"), 4)
        values.update(survived=int(self.survived), goal=int(self.goal),
                      started_on_target=int(self.started_on_target))
        for key in ("collided", "reached_target"):
            values[key] = int(values[key])
        values["closing_speed"] = "" if self.closing_speed is None else round(self.closing_speed, 4)
        return values


CSV_FIELDS = ("initial_lane", "episode", "seed", "steps", "return", "collided", "reached_target",
              "survived", "goal", "started_on_target", "duration", "target_lane", "start_lane",
              "vehicles", "crash_kind", "closing_speed")
"""Columns of the per-episode CSV (``episodes.csv`` in an evaluation folder)."""


def record_from_row(row: Mapping[str, Any]) -> EpisodeRecord:
    """Inverse of :meth:`EpisodeRecord.row` (values may be CSV strings)."""
    return EpisodeRecord(
        initial_lane=str(row["initial_lane"]), episode=int(row["episode"]), seed=int(row["seed"]),
        steps=int(row["steps"]), episode_return=float(row["return"]),
        collided=bool(int(row["collided"])), reached_target=bool(int(row["reached_target"])),
        duration=int(row["duration"]), target_lane=int(row["target_lane"]),
        start_lane=int(row["start_lane"]), vehicles=int(row["vehicles"]),
        crash_kind=str(row.get("crash_kind") or ""),  # CSVs written before the crash columns: none
        closing_speed=float(row["closing_speed"]) if row.get("closing_speed") not in (None, "") else None)


@dataclass
class Score:
    """Scores of one initial-lane setting."""

    episodes: int
    survival: int
    """Episodes without collision (count)."""
    goal: int
    """Episodes that reached the target lane (count)."""
    survival_score: float
    """Survival per 100 episodes (the paper's number)."""
    goal_score: float
    """Goal per 100 episodes."""
    mean_return: float
    mean_steps: float
    """Mean steps driven (Fig. 5's survival steps, at evaluation)."""


def score(records: Iterable[EpisodeRecord]) -> Score:
    """Survival and goal scores of a set of episodes."""
    recs = list(records)
    n = len(recs)
    if n == 0:
        raise ValueError("score: no episodes")
    survival = sum(r.survived for r in recs)
    goal = sum(r.goal for r in recs)
    return Score(episodes=n, survival=survival, goal=goal,
                 survival_score=100.0 * survival / n, goal_score=100.0 * goal / n,
                 mean_return=float(np.mean([r.episode_return for r in recs])),
                 mean_steps=float(np.mean([r.steps for r in recs])))


def scores_by_lane(records: Iterable[EpisodeRecord]) -> dict[str, Score]:
    """:func:`score` per initial-lane setting, in :data:`INITIAL_LANES` order."""
    recs = list(records)
    return {lane: score(r for r in recs if r.initial_lane == lane)
            for lane in INITIAL_LANES if any(r.initial_lane == lane for r in recs)}
