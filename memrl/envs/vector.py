"""gymnasium's vector API over the batched engine.

``gymnasium.make_vec("memrl/LaneChange-v0", num_envs=N, vectorization_mode="vector_entry_point",
config={...})`` returns :class:`LaneChangeVectorEnv`: the same observations, rewards, flags and
infos as ``SyncVectorEnv`` over N reference envs (numpy out, next-step autoreset as gymnasium
documents it), at the cost of one batched step. SB3 / CleanRL-style code uses it unchanged.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from gymnasium.error import ResetNeeded
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from memrl.envs.batched import BatchedLaneChange


class LaneChangeVectorEnv(VectorEnv):
    """N lane-change envs as one gymnasium ``VectorEnv`` (observations ``[N, frame_stack, H, W]``
    uint8, as the single env's).

    Args:
        num_envs: N >= 1.
        config: env config values (as for the single env).
        device: where the engine runs (``cpu``, ``cuda``, ...); outputs are numpy either way.
        render_mode: only None (full-scene pictures come from the single env).
    """

    metadata = {"render_modes": [], "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int = 1, config: dict[str, Any] | None = None, device: str = "cpu",
                 render_mode: str | None = None, **_: Any) -> None:
        if render_mode is not None:
            raise ValueError(f"render_mode={render_mode!r}: the vector env draws no scene pictures "
                             "(use gym.make for render_mode='rgb_array')")
        stack = int((config or {}).get("frame_stack", 1))
        self.engine = BatchedLaneChange(config, num_envs, device, frame_stack=max(stack, 1))
        self.num_envs = self.engine.num_envs
        b = self.engine.cfg.bev
        shape = (self.engine.frame_stack, b.height, b.width)
        self.single_observation_space = spaces.Box(0, 255, shape, np.uint8)
        self.single_action_space = spaces.Discrete(9)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.render_mode = None
        self._autoreset = np.zeros(self.num_envs, dtype=bool)
        self._was_reset = False  # step before reset: ResetNeeded, as SyncVectorEnv's envs

    def reset(self, *, seed: int | list[int | None] | None = None,
              options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset all envs (or ``options['reset_mask']``); ``seed`` as in ``SyncVectorEnv``."""
        if seed is None:
            seeds: list[int | None] = [None] * self.num_envs
        elif isinstance(seed, int | np.integer):
            seeds = [int(seed) + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
        if len(seeds) != self.num_envs:
            raise ValueError(f"{len(seeds)} seeds for num_envs={self.num_envs}")
        mask = np.ones(self.num_envs, dtype=bool)
        if options and "reset_mask" in options:
            mask = np.asarray(options["reset_mask"], dtype=bool)
        ids = np.flatnonzero(mask)
        self.engine.reset(ids.tolist(), [seeds[i] for i in ids])
        self._autoreset[ids] = False
        self._was_reset = True
        return self._obs(), self._info()

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """One step of every env; an env that finished at the last step is reset instead."""
        if not self._was_reset:
            raise ResetNeeded("Cannot call env.step() before calling env.reset()")
        actions = np.asarray(actions)
        ids = np.flatnonzero(self._autoreset)  # finished at the last step: reset instead
        out = self.engine.step(actions, active=torch.as_tensor(~self._autoreset), reset=ids.tolist())
        reward = out.reward.cpu().numpy()
        terminated = out.terminated.cpu().numpy()
        truncated = out.truncated.cpu().numpy()
        reward[ids], terminated[ids], truncated[ids] = 0.0, False, False
        self._autoreset = terminated | truncated
        return self._obs(), reward, terminated, truncated, self._info()

    def _obs(self) -> np.ndarray:
        if self.engine.frame_stack == 1:
            return self.engine.newest_frame()[:, None].cpu().numpy()
        return self.engine.observation().cpu().numpy()

    def _info(self) -> dict[str, Any]:
        """The single env's info keys, batched (with gymnasium's ``_key`` masks)."""
        state = self.engine.info()
        info: dict[str, Any] = {k: v.cpu().numpy() for k, v in state.items() if k != "rewards"}
        rewards = {name: value.cpu().numpy() for name, value in state["rewards"].items()}
        every = np.ones(self.num_envs, dtype=bool)
        info["rewards"] = {**rewards, **{f"_{name}": every for name in rewards}}
        info.update({f"_{k}": every for k in list(info) if not k.startswith("_")})
        return info
