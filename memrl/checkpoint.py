"""Trained agents as policies: load a run's Q-network and act greedily (or epsilon-greedily)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from memrl.dqn.checkpoint import CheckpointError
from memrl.envs.lane_change import LaneChangeEnv
from memrl.envs.vehicles import N_ACTIONS
from memrl.modules.policy import DrivingPolicy
from memrl.modules.qnet import QNetwork


def resolve(path: str | Path) -> Path:
    """A run folder, its ``checkpoints/`` folder or a ``final.pt`` file -> the ``final.pt``."""
    p = Path(path)
    for candidate in (p, p / "final.pt", p / "checkpoints" / "final.pt"):
        if candidate.is_file():
            return candidate
    raise CheckpointError(f"{path}: no trained network found (expected a run folder with "
                          "checkpoints/final.pt, or a final.pt file)")


def save_qnet(path: str | Path, net: QNetwork, env_cfg: dict[str, Any],
              extra: dict[str, Any] | None = None) -> Path:
    """Write a network in the ``final.pt`` format (``qnet`` weights, ``env`` config, extras)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"qnet": net.state_dict(), "env": env_cfg, **(extra or {})}, path)
    return path


def load_qnet(path: str | Path) -> tuple[QNetwork, dict[str, Any]]:
    """The Q-network of a finished run and the env config it was trained with."""
    file = resolve(path)
    try:
        state = torch.load(file, weights_only=False, map_location="cpu")
        net = QNetwork()
        net.load_state_dict(state["qnet"])
    except Exception as err:  # truncated file, foreign pickle, mismatched layers
        raise CheckpointError(f"{file}: not a memrl Q-network checkpoint ({err})") from err
    net.eval()
    return net, state.get("env", {})


class GreedyQPolicy(DrivingPolicy):
    """Acts with argmax Q on the stacked pixels (epsilon-greedy when ``epsilon > 0``)."""

    def __init__(self, net: QNetwork, epsilon: float = 0.0, seed: int = 0) -> None:
        self.net, self.epsilon = net, float(epsilon)
        self.rng = np.random.default_rng(seed)

    @torch.no_grad()
    def act(self, env: LaneChangeEnv, pixels: np.ndarray) -> int:
        if self.epsilon > 0 and self.rng.random() < self.epsilon:
            return int(self.rng.integers(N_ACTIONS))
        return int(self.net(torch.as_tensor(pixels)).argmax(-1))


def load_policy(path: str, epsilon: float = 0.0) -> DrivingPolicy:
    """A :class:`GreedyQPolicy` from a run folder or ``final.pt`` (used by deploy and evaluate)."""
    net, _ = load_qnet(path)
    return GreedyQPolicy(net, epsilon)
