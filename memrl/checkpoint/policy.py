"""Trained agents as policies: a run's Q-network acting greedily (or epsilon-greedily)."""

from __future__ import annotations

import numpy as np
import torch

from memrl.checkpoint.networks import load_qnet
from memrl.envs.lane_change import LaneChangeEnv
from memrl.envs.vehicles import N_ACTIONS
from memrl.modules.policy import DrivingPolicy, GreedyPolicy
from memrl.modules.qnet import input_frames


class GreedyQPolicy(DrivingPolicy):
    """Acts with argmax Q on the stacked pixels (epsilon-greedy when ``epsilon > 0``).

    ``policy.act(obs)`` takes a gym observation of ``gym.make("memrl/LaneChange-v0",
    config={"frame_stack": 4})`` directly; ``policy.act(env, pixels)`` is the
    :class:`DrivingPolicy` form that memrl's own runners use.
    """

    def __init__(self, net: torch.nn.Module, epsilon: float = 0.0, seed: int = 0) -> None:
        self.net, self.epsilon = net, float(epsilon)
        self.greedy = GreedyPolicy(net)  # the one greedy forward of evaluation and training drives
        self.rng = np.random.default_rng(seed)

    @torch.no_grad()
    def act(self, env: LaneChangeEnv | np.ndarray, pixels: np.ndarray | None = None) -> int:
        obs = np.asarray(env if pixels is None else pixels)
        frames = input_frames(self.net)
        if obs.dtype != np.uint8 or obs.shape[-3:] != (frames, 84, 84):
            raise ValueError(f"the policy takes uint8 observations of shape ({frames}, 84, 84), got "
                             f"{obs.dtype} {tuple(obs.shape)}: make the env with config={{'frame_stack': "
                             f"{frames}, 'frame_stride': <the run's env.frame_stride>}}")
        if self.epsilon > 0 and self.rng.random() < self.epsilon:
            return int(self.rng.integers(N_ACTIONS))
        return int(self.greedy.act_batch(torch.from_numpy(np.ascontiguousarray(obs))[None])[0])


def load_policy(path: str, epsilon: float = 0.0) -> DrivingPolicy:
    """A :class:`GreedyQPolicy` from a run folder or ``final.pt`` (used by deploy and evaluate)."""
    net, _ = load_qnet(path)
    return GreedyQPolicy(net, epsilon)
