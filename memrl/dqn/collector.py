"""Collection: N envs stepped together by the acting policy, with per-env episode totals.

``num_envs = 1`` steps the reference highway-env env through the TorchRL pipeline
(:func:`memrl.envs.torchrl_env.make_env`); ``num_envs = N > 1`` steps the batched engine as a
TorchRL env of batch size ``[N]`` on the run's device. Episode ``k`` (counted over all envs in
the order they start, lowest env index first) resets with :func:`episode_seed` ``(seed, k)``,
so episode k's scene is the same whatever N. Resets are lazy: an env whose episode ended is
reset at the start of the next step, so between steps no env is half reset and a checkpoint
can hold the engine as it is (N = 1: checkpoints fall between episodes, where there is no env
state to keep).

:meth:`Collector.collect_steps` is the same collection as a generator that pauses before each
env step, with the step's actions: runs whose envs are slices of one shared engine
(:mod:`memrl.envs.shared_engine`) submit them there and are stepped together.
"""

from __future__ import annotations

from collections.abc import Callable, Generator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import step_mdp

from memrl.data.transitions import to_transitions
from memrl.envs.torchrl_env import make_env, unwrap

Act = Callable[[TensorDictBase, int], None]
"""Sets ``td["action"]`` for the envs of ``td`` given the env steps done so far."""


def drive(gen: Generator[Any, None, Any]) -> Any:
    """Run ``gen`` to its end (its pauses need nothing: an engine of its own); its return value."""
    while True:
        try:
            next(gen)
        except StopIteration as end:
            return end.value


def episode_seed(seed: int, episode: int) -> int:
    """Reset seed of an episode: fixed by the run seed and the episode index."""
    return int(np.random.SeedSequence([int(seed), int(episode)]).generate_state(1)[0])


@dataclass
class EpisodeEnd:
    """Totals of one finished training episode."""

    env: int
    ret: float
    length: int
    collided: bool
    reached: bool
    frames: int
    """Env steps of the run (all envs) at the step that ended it."""


@dataclass
class Steps:
    """What one :meth:`Collector.collect` call gathered."""

    transitions: list[TensorDictBase] = field(default_factory=list)
    """One ``[N]`` tensordict per batched step (row i: env i), in step order."""
    episodes: list[EpisodeEnd] = field(default_factory=list)
    frames: int = 0


class Collector:
    """Steps ``num_envs`` envs with a policy and keeps each env's episode totals.

    Args:
        env_cfg: the run's env config node.
        num_envs: N (1: the reference env; more: the batched engine).
        device: the batched engine's device (N = 1 steps on the CPU).
        seed: the run seed (episode seeds derive from it).
        engine: N > 1: the engine to step (a slice of a shared engine) instead of a new one.
    """

    def __init__(self, env_cfg: Any, num_envs: int, device: torch.device, seed: int,
                 engine: Any | None = None) -> None:
        self.num_envs, self.seed = int(num_envs), int(seed)
        self.batched = self.num_envs > 1
        self.run_device = device
        """Where the policy acts and the transitions go (the reference env steps on the CPU)."""
        self.device = device if self.batched else torch.device("cpu")
        if engine is not None and not self.batched:
            raise ValueError("a shared engine's slice needs num_envs > 1")
        self.env = make_env(env_cfg, num_envs=self.num_envs, device=device, engine=engine) if self.batched \
            else make_env(env_cfg)
        n, dev = self.num_envs, self.device
        self.td: TensorDictBase | None = None
        self.pending = torch.ones(n, dtype=torch.bool, device=dev)
        """Envs whose episode ended (or never started): reset before the next step."""
        self.started = 0
        """Episodes started so far (the next reset takes the seed of this index)."""
        self.ret = torch.zeros(n, dtype=torch.float64, device=dev)
        self.length = torch.zeros(n, dtype=torch.long, device=dev)
        self.collided = torch.zeros(n, dtype=torch.bool, device=dev)
        self.reached = torch.zeros(n, dtype=torch.bool, device=dev)

    # ---------------------------------------------------------------- stepping
    def collect(self, act: Act, steps: int, frames: int, stop_at_episode_end: bool = False) -> Steps:
        """Up to ``steps`` batched steps (fewer with ``stop_at_episode_end`` when an episode
        ends); ``frames`` is the run's env steps before the first."""
        return drive(self.collect_steps(act, steps, frames, stop_at_episode_end))

    def collect_steps(self, act: Act, steps: int, frames: int, stop_at_episode_end: bool = False
                      ) -> Generator[torch.Tensor, None, Steps]:
        """:meth:`collect`, pausing before each env step with its actions (``[N]``)."""
        out = Steps()
        for _ in range(steps):
            self._reset_pending()
            td = self.td
            assert td is not None
            if td.device == self.run_device:
                act(td, frames + out.frames)
            else:  # the single env on the CPU, the network elsewhere
                on_device = td.to(self.run_device)
                act(on_device, frames + out.frames)
                td["action"] = on_device["action"].to(td.device)
            yield td["action"]
            td = self.env.step(td)
            out.frames += self.num_envs
            moved = td if self.batched else td.unsqueeze(0)
            out.transitions.append(to_transitions(moved).to(self.run_device))
            self._count(td["next"], frames + out.frames, out.episodes)
            self.td = step_mdp(td)
            if stop_at_episode_end and bool(self.pending.any()):
                break
        return out

    def _count(self, nxt: TensorDictBase, frames: int, ended: list[EpisodeEnd]) -> None:
        n = self.num_envs
        self.ret += nxt["reward"].reshape(n).to(torch.float64)
        self.length += 1
        self.collided |= nxt["collided"].reshape(n)
        self.reached |= nxt["reached_target"].reshape(n)
        done = nxt["done"].reshape(n)
        if not bool(done.any()):
            return
        for i in torch.nonzero(done).reshape(-1).tolist():
            ended.append(EpisodeEnd(i, float(self.ret[i]), int(self.length[i]),
                                    bool(self.collided[i]), bool(self.reached[i]), frames))
        self.pending |= done

    def _reset_pending(self) -> None:
        if not bool(self.pending.any()):
            return
        ids = torch.nonzero(self.pending).reshape(-1).tolist()
        seeds = [episode_seed(self.seed, self.started + j) for j in range(len(ids))]
        self.started += len(ids)
        if not self.batched:
            self.td = self.env.reset(seed=seeds[0])
        else:
            per_env: list[int | None] = [None] * self.num_envs
            for i, s in zip(ids, seeds, strict=True):
                per_env[i] = s
            self.env.base_env.seed_next_reset(per_env)
            if self.td is None:
                self.td = self.env.reset()
            else:
                self.td.set("_reset", self.pending.reshape(self.num_envs, 1))
                self.td = self.env.reset(self.td)
        for acc in (self.ret, self.length, self.collided, self.reached):
            acc[self.pending] = 0
        self.pending.zero_()

    # ---------------------------------------------------------------- pieces others use
    def learned_controller(self) -> Any | None:
        """The learned cars' controller (self-play adds snapshots to its pool), or None."""
        if self.batched:
            return self.env.base_env.engine.learned
        opponents = unwrap(self.env)._opponents
        return next((c for c in opponents.controllers if c.kind == "learned"), None) \
            if opponents is not None else None

    def between_episodes(self) -> bool:
        """Every env is done with its episode (N = 1 after an episode: a checkpoint point)."""
        return bool(self.pending.all())

    # ---------------------------------------------------------------- checkpoints
    def state_dict(self) -> dict[str, Any]:
        """Episode totals, the next seed index and (N > 1) the engine mid-episode."""
        state: dict[str, Any] = {"started": self.started, "pending": self.pending.cpu()}
        if not self.batched:
            if not self.between_episodes():  # the highway-env env cannot be saved mid-episode
                raise RuntimeError("a single-env checkpoint must fall between episodes")
            return state
        state.update(ret=self.ret.cpu(), length=self.length.cpu(), collided=self.collided.cpu(),
                     reached=self.reached.cpu(), engine=self.env.base_env.engine.state_dict(),
                     td=None if self.td is None else self.td.cpu())
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.started = int(state["started"])
        self.pending.copy_(state["pending"])
        if not self.batched:
            return
        for key in ("ret", "length", "collided", "reached"):
            getattr(self, key).copy_(state[key])
        self.env.base_env.engine.load_state_dict(state["engine"])
        self.td = None if state["td"] is None else state["td"].to(self.device)

    def close(self) -> None:
        self.env.close()
