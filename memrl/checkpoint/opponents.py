"""Other cars driven by earlier trained agents (Sec. IV-A: "copying the past trained agents").

Each learned car sees its own 84x84 BEV stack (rendered centred on it, its own target lane
highlighted, itself in the agent's shade) and acts with the 9 actions through one of the pool's
Q-networks. All learned cars of a step are served together: one batched forward pass per pool
network that some car uses, on that network's cars only.

Importing this module registers the ``learned`` kind of car controller with the env
(:func:`memrl.envs.controllers.register_controller`): the env makes learned cars from its
``opponent`` config without importing this package.
"""

from __future__ import annotations

import copy
import dataclasses
import glob
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from memrl.checkpoint.networks import load_qnet, resolve
from memrl.envs.config import LaneChangeConfig, OpponentConfig, validate_env_config
from memrl.envs.controllers import CarController, register_controller
from memrl.envs.stride import history_length, select_frames
from memrl.envs.vehicles import N_ACTIONS, CurvatureVehicle
from memrl.errors import UserError
from memrl.modules.qnet import decision_values

if TYPE_CHECKING:
    from memrl.envs.lane_change import LaneChangeEnv


class OpponentPoolError(UserError, ValueError):
    """A pool entry matches no checkpoint, or a checkpoint cannot drive a car."""


def expand_pool(pool: Sequence[str]) -> list[Path]:
    """Checkpoint files of the pool entries (run folders, ``final.pt`` files or globs)."""
    files: list[Path] = []
    for entry in pool:
        matches = sorted(glob.glob(str(entry))) if glob.has_magic(str(entry)) else [str(entry)]
        if not matches:
            raise OpponentPoolError(f"opponent.pool: no checkpoint matches {entry!r}")
        for match in matches:
            try:
                files.append(resolve(match))
            except ValueError as err:
                raise OpponentPoolError(f"opponent.pool: {err}") from err
    return files


def seen_view(env: Any) -> dict[str, Any] | None:
    """What a Q-network reads of an env config: every ``bev`` key (the drawing) and the frame
    stride. Keys an older run's config lacks take the env class's defaults, which draw what
    the versions before those keys drew; None for no config (a network saved by hand with
    ``save_qnet(path, net, {})``: its frames are unknown)."""
    if not isinstance(env, LaneChangeConfig):
        values = OmegaConf.to_container(env, resolve=True) if isinstance(env, DictConfig) else dict(env or {})
        if not values:
            return None
        env = validate_env_config({k: values[k] for k in ("bev", "frame_stride") if k in values})
    return {**{f"bev.{k}": v for k, v in dataclasses.asdict(env.bev).items()},
            "frame_stride": env.frame_stride}


def check_pool_views(trained: Sequence[tuple[Path, dict[str, Any] | None]], env: Any) -> None:
    """Refuse pool agents trained on other frames than ``env`` draws: a learned car's view is
    drawn with this env's BEV and stride, which such an agent never saw.

    Args:
        trained: (checkpoint file, :func:`seen_view` of the env it was trained in) per agent.
        env: the env config the learned cars drive in.
    """
    ours = seen_view(env or LaneChangeConfig())  # an empty config is the env class's defaults
    assert ours is not None
    for file, theirs in trained:
        if theirs is None:
            continue
        diff = [f"{k} {theirs.get(k)!r} there, {v!r} here" for k, v in ours.items() if theirs.get(k) != v]
        if diff:
            raise OpponentPoolError(f"opponent.pool: {file} was trained on other frames ({'; '.join(diff)}): "
                                    "learned cars need agents trained with this env's bev and frame_stride")


def pool_views(pool: Sequence[str]) -> list[tuple[Path, dict[str, Any] | None]]:
    """(checkpoint file, :func:`seen_view` of its training env) of every pool entry."""
    return [(file, seen_view(load_qnet(file)[1])) for file in expand_pool(pool)]


class LearnedCarController(CarController):
    """Drives cars with greedy (or epsilon-greedy) Q-networks of past agents.

    Args:
        pool: checkpoint entries (see :func:`expand_pool`) or already built networks.
        epsilon: probability of a uniformly random action per car and step.
    """

    kind = "learned"

    def __init__(self, pool: Sequence[str | torch.nn.Module], epsilon: float = 0.0) -> None:
        nets: list[torch.nn.Module] = []
        self.trained_on: list[tuple[Path, dict[str, Any] | None]] = []
        """(file, :func:`seen_view` of its training env) of each agent loaded from a file."""
        for entry in pool:
            if isinstance(entry, torch.nn.Module):
                nets.append(entry)
                continue
            for file in expand_pool([entry]):
                net, env = load_qnet(file)
                nets.append(net)
                self.trained_on.append((file, seen_view(env)))
        if not nets:
            raise OpponentPoolError("opponent.pool is empty: learned cars need past agents")
        self.epsilon = float(epsilon)
        self.forward_calls = 0
        """Number of batched forward passes made (one per step with learned cars)."""
        self._set_networks(nets)

    def _set_networks(self, nets: list[torch.nn.Module]) -> None:
        # channels-last weights: the same Q-values, several times faster convs on CPU
        self.networks = [n.eval().to(memory_format=torch.channels_last)  # type: ignore[call-overload]
                         for n in nets]

    def check_view(self, env: Any) -> None:
        """Refuse (one line) pool agents trained on other frames than ``env`` draws."""
        check_pool_views(self.trained_on, env)

    def to(self, device: torch.device | str) -> LearnedCarController:
        """Move the pool's networks to ``device`` (the batched engine's); returns self."""
        self._set_networks([n.to(device) for n in self.networks])
        return self

    @property
    def device(self) -> torch.device:
        return next(self.networks[0].parameters()).device

    def add_network(self, net: torch.nn.Module) -> None:
        """Add a snapshot (e.g. of the agent being trained) to the pool; used from the next
        episode on."""
        self._set_networks([*self.networks, copy.deepcopy(net).to(self.device)])

    @torch.no_grad()
    def q_values(self, model_index: torch.Tensor, stacks: torch.Tensor) -> torch.Tensor:
        """Q-values ``[N, 9]``: car i through network ``model_index[i]``; one batched forward
        per network on its own cars (so each car costs one network's forward, equal to that
        network run alone; ``vmap`` over the pool ran every network on every car, and measured
        10-20x slower on CPU: ``python -m memrl.bench pool``)."""
        self.forward_calls += 1
        # in chunks: past ~64 stacks the activations outgrow the caches and each costs more
        out = torch.empty(len(stacks), N_ACTIONS, device=stacks.device)
        for index in model_index.unique().tolist():
            cars = model_index == index
            out[cars] = torch.cat([decision_values(self.networks[index], part)  # a risk critic: safe choice
                                   for part in stacks[cars].split(64)])
        return out

    def reset(self, env: LaneChangeEnv, cars: Sequence[CurvatureVehicle]) -> None:
        """A new episode: each car's network and target lane were drawn with the scene
        (:func:`memrl.envs.scene.sample_scene`); its frame stack starts afresh."""
        for car in cars:
            car.frames = None

    def _stack(self, env: LaneChangeEnv, car: CurvatureVehicle) -> np.ndarray:
        frame = env.observe_from(car, car.target_lane)
        if frame.shape[0] == 3:  # RGB drawing: the same gray levels as the agent's pipeline
            from torchrl.envs.transforms.functional import rgb_to_grayscale

            frame = rgb_to_grayscale(torch.from_numpy(frame)).numpy()
        # the stride the agent (and so the network) was trained with: the env config's
        stride = env.cfg.frame_stride
        if car.frames is None:  # like CatFrames(padding="same") at reset
            car.frames = np.repeat(frame, history_length(4, stride), axis=0)
        else:
            car.frames = np.concatenate([car.frames[1:], frame])
        return select_frames(car.frames, 1, stride)

    def act(self, env: LaneChangeEnv, cars: Sequence[CurvatureVehicle]) -> np.ndarray:
        stacks = torch.from_numpy(np.stack([self._stack(env, car) for car in cars]))
        index = torch.tensor([car.policy_index for car in cars])
        actions = self.q_values(index, stacks).argmax(-1).numpy()
        if self.epsilon > 0:
            rng = env.np_random
            explore = rng.random(len(cars)) < self.epsilon
            actions = np.where(explore, rng.integers(N_ACTIONS, size=len(cars)), actions)
        return actions.astype(np.int64)


def learned_cars(cfg: OpponentConfig) -> LearnedCarController:
    """The env's controller of ``learned`` cars: its ``opponent.pool`` and ``epsilon``."""
    return LearnedCarController(cfg.pool, epsilon=cfg.epsilon)


register_controller("learned", learned_cars)
