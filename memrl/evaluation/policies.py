"""What ``memrl.evaluate`` can evaluate: trained runs, the scripted driver, random, a human.

The ``policy`` config group instantiates a *source* (``_target_``); a source yields one or
more :class:`Candidate` s, each an :class:`~memrl.evaluation.runner.Actor` with the env config
it must be evaluated in, the row label of Table III and where its results go:

* :class:`CheckpointSource`: every finished training run under the given folders (a run
  folder or a whole multirun), greedy; label = the run's mode (Default, A, B); env = the
  run's own ``config.yaml``; results in ``<run>/eval/``.
* :class:`DriverSource`: any :class:`~memrl.modules.policy.DrivingPolicy` made fresh for
  every episode (scripted driver, uniform random); results in the Hydra run folder.
* :class:`HumanSource`: a person at the keyboard (the recorder's window), one episode at a
  time; several people are rows of one label with different ``person`` (like seeds).
"""

from __future__ import annotations

import functools
import logging
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import OmegaConf

from memrl.checkpoint import load_qnet, recorded_config
from memrl.envs.lane_change import LaneChangeEnv
from memrl.errors import UserError, load_run_config
from memrl.evaluation.protocol import eval_subdir
from memrl.evaluation.rows import row_label
from memrl.evaluation.runner import Actor
from memrl.modes import MODES
from memrl.modules.policy import DrivingPolicy, GreedyPolicy
from memrl.modules.risk import safe_choice

log = logging.getLogger(__name__)



class GreedyActor(Actor):
    """argmax Q of a Q-network over a whole batch in one forward pass (the trained agent):
    :class:`~memrl.modules.policy.GreedyPolicy` as an actor. It acts from pixels alone, so
    :func:`~memrl.evaluation.runner.run_jobs` runs it on the batched engine.

    Args:
        net: the Q-network.
        device: where it runs.
        gamma: the discount its Q-values estimate (the run's ``agent.gamma``): with it the
            protocol evaluation records the crash-sight section
            (:mod:`memrl.evaluation.crash_sight`); None: not recorded.
    """

    tensor_policy = True
    gives_values = True

    def __init__(self, net: torch.nn.Module, device: torch.device | str = "cpu",
                 gamma: float | None = None) -> None:
        self.policy = GreedyPolicy(net, device)
        self.gamma = gamma
        self._risk: bool | None = None  # the network declares a "risk" output (found at the first call)

    @property
    def net(self) -> torch.nn.Module:
        """The network it acts with (a channels-last copy)."""
        return self.policy.net

    def to(self, device: torch.device | str) -> GreedyActor:
        self.policy.to(device)
        return self

    def act_pixels(self, pixels: torch.Tensor) -> torch.Tensor:
        return self.policy.act_batch(pixels)

    def act_values(self, pixels: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Greedy actions and the expected Q-values they maximise (the forward acting uses);
        for a network whose ``outputs`` declare ``"risk"``, its declared outputs instead, the
        risk among them (one forward either way)."""
        if self._risk is None:
            self._risk = "risk" in self.policy.outputs(pixels[:1])
        if self._risk:  # a crash-risk critic acts on its safe choice (memrl.modules.risk)
            out = self.policy.outputs(pixels)
            values = {"q": out["q"], "risk": out["risk"]}
            threshold = getattr(self.policy.net, "threshold", None)
            if threshold is not None:
                return safe_choice(out["q"], out["risk"], float(threshold)).argmax(-1), values
        else:
            values = {"q": self.policy.q_values(pixels)}
        return values["q"].argmax(-1), values

    def act(self, slots: Sequence[int], envs: Sequence[LaneChangeEnv], pixels: np.ndarray) -> np.ndarray:
        return self.policy.act_batch(torch.from_numpy(pixels)).cpu().numpy()


class RollInActor(GreedyActor):
    """JSRL's combined policy: ``teacher`` greedy for the first ``h`` steps of each episode,
    then ``net`` greedy; it needs each episode's step (``act_steps``), which the batched
    engine gives (:func:`memrl.evaluation.engine_runner.run_jobs_on_engine`)."""

    gives_values = False
    needs_steps = True

    def __init__(self, teacher: torch.nn.Module, net: torch.nn.Module, h: int,
                 device: torch.device | str = "cpu") -> None:
        super().__init__(net, device)
        self.teacher, self.h = GreedyPolicy(teacher, device), int(h)

    def to(self, device: torch.device | str) -> RollInActor:
        self.teacher.to(device)
        super().to(device)
        return self

    def act_steps(self, pixels: torch.Tensor, steps: torch.Tensor) -> torch.Tensor:
        """Actions ``[N]`` for observations at episode steps ``steps`` ``[N]`` (0: the first)."""
        own, guide = self.policy.act_batch(pixels), self.teacher.act_batch(pixels)
        return torch.where(steps.to(own.device) < self.h, guide, own)

    def act(self, slots: Sequence[int], envs: Sequence[LaneChangeEnv], pixels: np.ndarray) -> np.ndarray:
        raise TypeError("RollInActor acts on the batched engine only (it needs each episode's step)")


def run_gamma(cfg: dict[str, Any]) -> float | None:
    """The discount a run's Q-values estimate: its config's ``agent.gamma`` (None when the
    config records none: the crash-sight section is then not recorded)."""
    gamma = (cfg.get("agent") or {}).get("gamma")
    return None if gamma is None else float(gamma)


def policy_seed(seed: int) -> int:
    """Seed of a stochastic policy in the episode of scene ``seed``: independent of the scene's
    own draws (gymnasium seeds the env's generator exactly like ``default_rng(seed)``)."""
    return int(np.random.SeedSequence([int(seed), 0xAC7]).generate_state(1)[0])


class DriverActor(Actor):
    """A fresh driving policy per episode (per slot of the batch).

    Args:
        factory: makes the policy; called as ``factory(seed=...)`` when ``seeded``.
        seeded: pass a seed derived from the scene's seed (stochastic policies), so that an
            episode's actions do not depend on how episodes were batched or split.
    """

    def __init__(self, factory: Callable[..., DrivingPolicy], seeded: bool = False) -> None:
        self.factory, self.seeded = factory, seeded
        self.policies: dict[int, DrivingPolicy] = {}

    def begin(self, slot: int, env: LaneChangeEnv, seed: int) -> None:
        policy = self.factory(seed=policy_seed(seed)) if self.seeded else self.factory()
        policy.reset(env)
        self.policies[slot] = policy

    def act(self, slots: Sequence[int], envs: Sequence[LaneChangeEnv], pixels: np.ndarray) -> np.ndarray:
        return np.array([self.policies[s].act(env, px) for s, env, px in zip(slots, envs, pixels,
                                                                              strict=True)])


class HumanActor(Actor):
    """One keyboard driver for all episodes, one episode at a time, in this process."""

    batchable = False
    parallel = False
    needs_render = True

    def __init__(self, driver: DrivingPolicy) -> None:
        self.driver = driver
        self.total, self.started = 0, 0

    def plan(self, total: int, done: int = 0) -> None:
        """Episodes of the whole protocol and those finished in earlier sittings (for the window)."""
        self.total, self.started = total, done
        if hasattr(self.driver, "kept_label"):
            self.driver.kept_label = "finished before"

    def begin(self, slot: int, env: LaneChangeEnv, seed: int) -> None:
        if hasattr(self.driver, "progress") and self.total:
            self.driver.progress = (self.started + 1, self.total, self.started)
        self.started += 1
        self.driver.reset(env)

    def act(self, slots: Sequence[int], envs: Sequence[LaneChangeEnv], pixels: np.ndarray) -> np.ndarray:
        return np.array([self.driver.act(envs[0], pixels[0])])

    def close(self) -> None:
        close = getattr(self.driver, "close", None)
        if callable(close):
            close()


@dataclass
class Candidate:
    """One policy to evaluate."""

    name: str
    """Row label in Table III (Default, A, B, scripted, random, human, ...)."""
    actor: Actor
    env: dict[str, Any] | None = None
    """Base env config (None: the evaluate config's ``env``)."""
    out_dir: Path | None = None
    """Where results go (None: the Hydra run folder)."""
    meta: dict[str, Any] = field(default_factory=dict)
    """Written into eval.json: kind, run, mode, train seed, person, policy config."""


class PolicySource(ABC):
    """Instantiated from the ``policy`` config group."""

    @abstractmethod
    def candidates(self) -> list[Candidate]:
        """The policies to evaluate."""


class RunNotFoundError(UserError, FileNotFoundError):
    """``policy.run`` names no folder, or none with a finished run (``checkpoints/final.pt``)."""


def find_runs(paths: str | Path | Sequence[str | Path]) -> list[Path]:
    """Finished training runs (folders with ``checkpoints/final.pt``) at or below ``paths``."""
    items = [paths] if isinstance(paths, str | Path) else list(paths)
    runs: list[Path] = []
    for item in items:
        p = Path(item)
        if not p.exists():
            raise RunNotFoundError(f"policy 'run': no such folder {p}")
        if (p / "checkpoints" / "final.pt").is_file():
            runs.append(p)
        else:
            runs += sorted(f.parent.parent for f in p.glob("**/checkpoints/final.pt"))
    if not runs:
        raise RunNotFoundError(f"policy 'run': no finished training run (checkpoints/final.pt) in "
                               f"{', '.join(map(str, items))}")
    return sorted(dict.fromkeys(r.resolve() for r in runs))


def run_config(run: Path) -> dict[str, Any]:
    """A run's resolved config as a plain dict: its ``config.yaml``; without it, what the run
    recorded elsewhere (:func:`recorded_config`), or a one-line refusal naming ``config.yaml``
    (never a guess: a run without its config is not labelled Default)."""
    path = run / "config.yaml"
    if path.is_file():
        return OmegaConf.to_container(load_run_config(path))  # type: ignore[return-value]
    cfg, source = recorded_config(run)
    if cfg is None:
        raise UserError(f"{path}: missing, and neither a checkpoint (checkpoints/last) nor "
                        "checkpoints/final.pt or summary.json records the run's mode and seed; "
                        "restore config.yaml (the run's row, seed and env come from it)")
    log.warning("%s: missing; the run's mode, seed and env are read from %s", path, source)
    return cfg


def run_label(cfg: dict[str, Any]) -> str:
    """Table III row label of a run config: its mode (Default, A, B), its study variant if any
    and the traffic it was trained among when that is not constant-speed cars: ``A (mixed)``,
    ``A (cue)`` (:func:`~memrl.evaluation.rows.row_label`)."""
    mode = str(cfg.get("mode", {}).get("name", "default"))
    opponent = (cfg.get("env") or {}).get("opponent", "constant")
    traffic = opponent.get("type", "constant") if isinstance(opponent, dict) else str(opponent)
    variant = cfg.get("variant")
    label = MODES[mode].label if mode in MODES else mode  # the mode's own Table III label
    return row_label(label, str(traffic), str(variant) if variant else None)


DEFAULT_SUBDIR = eval_subdir("constant")
"""A trained run's evaluation folder under the paper's constant-speed test cars."""


class CheckpointSource(PolicySource):
    """Greedy policies of finished training runs.

    Args:
        run: a run folder, a folder holding runs (a multirun), or a list of them.
        name: row label; None: the run's mode (Default, A, B).
        subdir: results folder inside each run; None: ``eval`` (:data:`DEFAULT_SUBDIR`), which
            ``memrl.evaluate`` turns into ``eval_<type>`` for test traffic other than the
            paper's constant-speed cars (``eval_mixed``, as the study names it).
    """

    def __init__(self, run: str | Sequence[str], name: str | None = None, subdir: str | None = None) -> None:
        self.runs = find_runs(run if isinstance(run, str) else list(run))
        self.name, self.subdir = name, subdir

    def candidates(self) -> list[Candidate]:
        out = []
        for run in self.runs:
            net, ckpt_env = load_qnet(run)
            cfg = run_config(run)
            mode = str(cfg.get("mode", {}).get("name", "default"))
            label = run_label(cfg)  # rows are grouped by the traffic trained among: "A (mixed)"
            out.append(Candidate(
                name=self.name or label, actor=GreedyActor(net, gamma=run_gamma(cfg)),
                env=cfg.get("env") or ckpt_env, out_dir=run / (self.subdir or DEFAULT_SUBDIR),
                meta={"kind": "checkpoint", "run": str(run), "mode": mode,
                      "train_seed": cfg.get("seed"), "unit": f"seed {cfg.get('seed')}"}))
        return out


class DriverSource(PolicySource):
    """A driving policy made fresh for every episode (e.g. the scripted driver, random).

    Args:
        name: row label.
        driver: a factory of the policy (Hydra ``_partial_: true``).
        seeded: pass ``seed=`` (derived from the scene's seed) to the factory.
        unit: what distinguishes several evaluations of this label (e.g. a parameter setting).
    """

    def __init__(self, name: str, driver: Callable[..., DrivingPolicy], seeded: bool = False,
                 unit: str | None = None) -> None:
        self.name, self.driver, self.seeded, self.unit = name, driver, seeded, unit

    def candidates(self) -> list[Candidate]:
        target = self.driver.func if isinstance(self.driver, functools.partial) else self.driver
        return [Candidate(self.name, DriverActor(self.driver, self.seeded),
                          meta={"kind": "driver", "unit": self.unit or self.name,
                                "driver": f"{target.__module__}.{target.__qualname__}"})]


class HumanSource(PolicySource):
    """A person driving with the arrow keys in the recorder's window.

    Args:
        driver: the keyboard driver (``memrl.modules.human.KeyboardDriver``).
        name: row label.
        person: who drove; the report averages over people as over training seeds.
    """

    def __init__(self, driver: DrivingPolicy, name: str = "human", person: str | None = None) -> None:
        self.driver, self.name, self.person = driver, name, person

    def candidates(self) -> list[Candidate]:
        return [Candidate(self.name, HumanActor(self.driver),
                          meta={"kind": "human", "person": self.person,
                                "unit": self.person or "anonymous"})]
