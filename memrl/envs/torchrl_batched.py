"""TorchRL face of the batched engine: an ``EnvBase`` with batch size ``[N]``.

Built by :func:`memrl.envs.torchrl_env.make_env` with ``num_envs=N``; its keys are those of
the single-env pipeline with a leading env dimension: ``pixels`` uint8 ``[N, 4, H, W]`` (the
engine's own frame stack, oldest first, ``frame_stride`` steps apart), ``action``,
``reward``, ``done`` / ``terminated`` / ``truncated``, the flags of
:data:`~memrl.envs.torchrl_env.INFO_KEYS`, and, from the ``StepCounter`` / ``RewardSum``
transforms, ``step_count`` and ``episode_reward``. Envs are
reset by TorchRL's ``_reset`` mask (``step_and_maybe_reset`` / rollouts do it).
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from memrl.envs.batched import INFO_KEYS, BatchedLaneChange
from memrl.envs.vehicles import N_ACTIONS


class BatchedLaneChangeEnv(EnvBase):
    """N lane-change envs stepped together on one device, as one TorchRL env.

    Args:
        config: env config values.
        num_envs: N >= 1.
        device: ``auto``, ``cpu``, ``cuda`` or ``cuda:K`` (engine, specs and outputs).
        frame_stack: frames per ``pixels`` stack.
        engine: the engine to step instead of a new one (a run's slice of a shared engine,
            :class:`~memrl.envs.shared_engine.EngineSlice`, of ``num_envs`` envs).
    """

    def __init__(self, config: dict[str, Any] | None, num_envs: int, device: Any = "cpu",
                 frame_stack: int = 4, engine: Any | None = None) -> None:
        if engine is not None and engine.num_envs != num_envs:
            raise ValueError(f"an engine of {engine.num_envs} envs for num_envs={num_envs}")
        if engine is None:
            engine = BatchedLaneChange(config, num_envs, device, frame_stack)
        super().__init__(device=engine.device, batch_size=torch.Size([engine.num_envs]))
        self.engine = engine
        n, b = engine.num_envs, engine.cfg.bev
        flags = {k: Unbounded(shape=(n,), dtype=torch.bool, device=self.device) for k in INFO_KEYS}
        self.observation_spec = Composite(
            pixels=Bounded(0, 255, (n, frame_stack, b.height, b.width), dtype=torch.uint8,
                           device=self.device),
            **flags, shape=(n,), device=self.device)
        self.action_spec = Categorical(N_ACTIONS, shape=(n,), dtype=torch.int64, device=self.device)
        self.reward_spec = Unbounded(shape=(n, 1), dtype=torch.float32, device=self.device)
        self.done_spec = Composite(
            {k: Categorical(2, shape=(n, 1), dtype=torch.bool, device=self.device)
             for k in ("done", "terminated", "truncated")}, shape=(n,), device=self.device)
        self._seeds: list[int | None] | None = None

    def _set_seed(self, seed: int | None) -> None:
        """Env i's next reset draws the scene of seed ``seed + i`` (as ``SyncVectorEnv``)."""
        self._seeds = None if seed is None else [int(seed) + i for i in range(self.engine.num_envs)]

    def seed_next_reset(self, seeds: list[int | None]) -> None:
        """Seeds of the next reset, one per env (None: that env continues its generator); the
        trainer gives every episode the seed of its index so that scenes do not depend on N."""
        if len(seeds) != self.engine.num_envs:
            raise ValueError(f"{len(seeds)} seeds for {self.engine.num_envs} envs")
        self._seeds = list(seeds)

    def _reset(self, tensordict: TensorDictBase | None = None, **_: Any) -> TensorDictBase:
        mask = None if tensordict is None else tensordict.get("_reset", None)
        if mask is None:
            ids = list(range(self.engine.num_envs))
        else:
            ids = torch.nonzero(mask.reshape(self.engine.num_envs), as_tuple=True)[0].tolist()
        seeds = None if self._seeds is None else [self._seeds[i] for i in ids]
        self._seeds = None
        self.engine.reset(ids, seeds)
        info = self.engine.info()
        flags = {k: torch.zeros(self.batch_size + (1,), dtype=torch.bool, device=self.device)
                 for k in ("done", "terminated", "truncated")}
        return TensorDict({"pixels": self.engine.observation(), **{k: info[k] for k in INFO_KEYS}, **flags},
                          batch_size=self.batch_size, device=self.device)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        out = self.engine.step(tensordict.get("action"))
        terminated, truncated = out.terminated[:, None], out.truncated[:, None]
        return TensorDict({"pixels": self.engine.observation(),
                           "reward": out.reward.to(torch.float32)[:, None],
                           "done": terminated | truncated, "terminated": terminated, "truncated": truncated,
                           "collided": out.collided, "on_target_lane": out.on_target_lane,
                           "reached_target": out.reached_target,
                           }, batch_size=self.batch_size, device=self.device)
