"""Other libraries' agents under the Table III protocol: ``policy=python`` and ``policy=sb3``.

An agent trained on ``gym.make("memrl/LaneChange-v0", config={...})`` meets exactly the scenes
memrl's own runs meet, and its evaluation folder (``eval.json``, ``episodes.csv``) goes into a
report beside theirs (``docs/evaluation.md``):

* :class:`PythonSource`: ``target="<module>:<factory>"``; ``factory(**kwargs)`` returns an agent
  with ``act(obs) -> action`` (one gymnasium observation, uint8 ``[4, 84, 84]``, in; an action
  index 0-8 out) or ``act_pixels(pixels) -> actions`` (a uint8 tensor ``[B, 4, 84, 84]`` in, int
  ``[B]`` out: the batched engine runs it, all episodes of a lane at once).
* :class:`SB3Source`: a Stable-Baselines3 model ``.zip`` (``pip install memrl[sb3]``), acting with
  ``model.predict(obs, deterministic=True)`` on a whole batch of observations.

``env`` is the ``config`` the agent was trained with in ``gym.make`` (memrl's gym defaults
below it, so ``{}`` is the plain gym env); the protocol's episode rules go on top, as for every
policy. The runners stack the frames (4, oldest first, the first repeated after a reset, as the
gym env's ``frame_stack: 4``). The agent is built again in each worker process from ``target``
(or ``path``), so it need not be picklable.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import OmegaConf

from memrl.envs.config import EnvConfigError, env_config_dict, validate_env_config
from memrl.envs.lane_change import LaneChangeEnv
from memrl.envs.vehicles import N_ACTIONS
from memrl.errors import UserError
from memrl.evaluation.jobs import Actor
from memrl.evaluation.policies import Candidate, PolicySource

FRAMES = 4
"""Frames per observation the runners stack (the gym env's ``frame_stack``)."""


def import_target(target: str, key: str = "policy.target") -> Any:
    """The object named by ``"<module>:<name>"`` (or ``"<module>.<name>"``), in one line on failure."""
    module, sep, name = target.partition(":")
    if not sep:
        module, _, name = target.rpartition(".")
    if not module or not name:
        raise UserError(f"config '{key}': give '<module>:<factory>', got {target!r}")
    try:
        obj: Any = importlib.import_module(module)
        for part in name.split("."):
            obj = getattr(obj, part)
    except (ImportError, AttributeError) as err:
        raise UserError(f"config '{key}': cannot import {target!r} ({type(err).__name__}: {err})") from None
    return obj


def agent_env(env: Mapping[str, Any] | None, key: str = "policy.env") -> dict[str, Any]:
    """The whole env config of an agent trained with ``gym.make(..., config=env)``: memrl's gym
    defaults with ``env`` merged in, one frame per env step (the runners stack ``FRAMES``)."""
    values = dict(OmegaConf.to_container(OmegaConf.create(dict(env or {})), resolve=True))  # type: ignore[arg-type]
    stack = values.pop("frame_stack", FRAMES)
    if stack != FRAMES:
        raise UserError(f"config '{key}.frame_stack': the protocol gives agents {FRAMES} stacked frames, "
                        f"got {stack}")
    merged: dict[str, Any] = OmegaConf.to_container(  # type: ignore[assignment]
        OmegaConf.merge(OmegaConf.create(env_config_dict()), OmegaConf.create(values)))
    merged["frame_stack"] = 1
    try:
        validate_env_config(merged)
    except EnvConfigError as err:
        raise UserError(f"config '{key}': {err}") from None
    return merged


def as_actions(out: Any, count: int, who: str) -> np.ndarray:
    """An agent's output as ``count`` action indices, refused in one line when it is not."""
    actions = np.asarray(out.cpu() if isinstance(out, torch.Tensor) else out).reshape(-1)
    if actions.shape != (count,) or not np.isin(actions, np.arange(N_ACTIONS)).all():
        raise UserError(f"{who} returned {out!r}: want {count} action index(es) in 0-{N_ACTIONS - 1}")
    return actions.astype(np.int64)


class LazyAgent(Actor):
    """An actor around an agent that is rebuilt (not pickled) in every process it runs in."""

    def __init__(self) -> None:
        self._agent: Any = None

    def build(self) -> Any:
        """Make the agent (in this process)."""
        raise NotImplementedError

    @property
    def agent(self) -> Any:
        if self._agent is None:
            self._agent = self.build()
        return self._agent

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "_agent": None}


class PythonActor(LazyAgent):
    """``factory(**kwargs)``'s agent: ``act(obs)`` per observation, or ``act_pixels`` on a batch."""

    def __init__(self, target: str, kwargs: Mapping[str, Any] | None = None) -> None:
        super().__init__()
        self.target, self.kwargs = target, dict(kwargs or {})
        agent = self.agent  # built once here: a bad target or factory fails before any episode
        if not callable(getattr(agent, "act_pixels", None)) and not callable(getattr(agent, "act", None)):
            raise UserError(f"config 'policy.target': {target}() gave a {type(agent).__name__} with neither "
                            f"act(obs) nor act_pixels(pixels)")
        self.tensor_policy = callable(getattr(agent, "act_pixels", None))

    def build(self) -> Any:
        factory = import_target(self.target)
        try:
            return factory(**self.kwargs)
        except Exception as err:  # the user's own code: its first line, not a traceback into memrl
            first = (str(err).strip().splitlines() or [""])[0]
            raise UserError(f"config 'policy.target': {self.target}(**policy.kwargs) failed "
                            f"({type(err).__name__}: {first})") from None

    def act_pixels(self, pixels: torch.Tensor) -> torch.Tensor:
        actions = as_actions(self.agent.act_pixels(pixels), len(pixels), f"{self.target}: act_pixels")
        return torch.from_numpy(actions).to(pixels.device)

    def act(self, slots: Sequence[int], envs: Sequence[LaneChangeEnv], pixels: np.ndarray) -> np.ndarray:
        if self.tensor_policy:
            return self.act_pixels(torch.from_numpy(pixels)).cpu().numpy()
        return np.concatenate([as_actions(self.agent.act(obs), 1, f"{self.target}: act") for obs in pixels])


class SB3Actor(LazyAgent):
    """A Stable-Baselines3 model: ``predict`` on the whole batch of observations."""

    def __init__(self, path: str, algo: str = "DQN", device: str = "cpu", deterministic: bool = True) -> None:
        super().__init__()
        self.path, self.algo, self.device, self.deterministic = path, algo, device, deterministic
        self.agent  # noqa: B018  (loaded once here: a bad file or algorithm fails before any episode)

    def build(self) -> Any:
        try:
            import stable_baselines3
        except ImportError:
            raise UserError("policy=sb3 needs Stable-Baselines3: pip install 'memrl[sb3]'") from None
        cls = getattr(stable_baselines3, self.algo, None)
        if not isinstance(cls, type):
            raise UserError(f"config 'policy.algo': {self.algo!r} is not a Stable-Baselines3 algorithm "
                            f"(e.g. DQN, PPO, A2C, QRDQN from sb3-contrib is not loaded here)")
        if not Path(self.path).is_file():
            raise UserError(f"config 'policy.path': no such file {self.path}")
        try:
            return cls.load(self.path, device=self.device)
        except Exception as err:  # a zip of another algorithm, a truncated or foreign file
            first = (str(err).strip().splitlines() or [type(err).__name__])[0]
            raise UserError(f"{self.path}: not a Stable-Baselines3 {self.algo} model ({first})") from None

    def act(self, slots: Sequence[int], envs: Sequence[LaneChangeEnv], pixels: np.ndarray) -> np.ndarray:
        actions, _ = self.agent.predict(pixels, deterministic=self.deterministic)
        return as_actions(actions, len(pixels), f"{self.path}: predict")


class PythonSource(PolicySource):
    """Any agent object from your code (``conf/policy/python.yaml``).

    Args:
        target: ``"<module>:<factory>"``; ``factory(**kwargs)`` returns the agent.
        kwargs: keyword arguments of the factory.
        env: the ``config`` the agent was trained with in ``gym.make``.
        name: row label (None: the factory's name).
        unit: what tells several evaluations of one row apart, as seeds do (None: ``target``).
    """

    def __init__(self, target: str, kwargs: Mapping[str, Any] | None = None,
                 env: Mapping[str, Any] | None = None, name: str | None = None,
                 unit: str | None = None) -> None:
        self.env = agent_env(env)
        self.actor = PythonActor(target, kwargs)
        self.name = name or target.replace(":", ".").rsplit(".", 1)[-1]
        self.unit, self.target = unit or target, target

    def candidates(self) -> list[Candidate]:
        return [Candidate(self.name, self.actor, env=self.env,
                          meta={"kind": "python", "target": self.target, "unit": self.unit})]


class SB3Source(PolicySource):
    """A Stable-Baselines3 model file (``conf/policy/sb3.yaml``).

    Args:
        path: the model's ``.zip`` (``model.save(path)``).
        algo: its Stable-Baselines3 class (DQN, PPO, A2C, ...).
        env: the ``config`` the model was trained with in ``gym.make``.
        name: row label (None: ``SB3 <algo>``).
        unit: what tells several models of one row apart (None: the file's name).
        deterministic: ``predict(..., deterministic=...)``.
    """

    def __init__(self, path: str, algo: str = "DQN", env: Mapping[str, Any] | None = None,
                 name: str | None = None, unit: str | None = None, deterministic: bool = True) -> None:
        self.env = agent_env(env)
        self.actor = SB3Actor(str(path), algo, deterministic=deterministic)
        self.name = name or f"SB3 {algo}"
        self.unit, self.path = unit or Path(path).stem, str(Path(path).resolve())

    def candidates(self) -> list[Candidate]:
        return [Candidate(self.name, self.actor, env=self.env,
                          meta={"kind": "sb3", "path": self.path, "unit": self.unit})]
