"""The Q-network of Table I and its TorchRL actor."""

from __future__ import annotations

import torch
from torch import nn
from torchrl.data import Categorical
from torchrl.modules import QValueActor

from memrl.envs.vehicles import N_ACTIONS


class QNetwork(nn.Module):
    """Table I: three 3x3 conv layers of 16 filters, each ReLU + 2x2 max-pool, FC 256, 9 outputs.

    Padding 1 ("same") keeps each conv's size, so 84 -> 42 -> 21 -> 10 after the three pools
    (the last pool floors 21 / 2); the FC layer sees 16 x 10 x 10 = 1600 features. Input is
    uint8 ``[..., frames, H, W]``, scaled to [0, 1] inside the module.
    """

    def __init__(self, frames: int = 4, size: int = 84, n_actions: int = N_ACTIONS,
                 channels: int = 16, hidden: int = 256, pool_first: bool = True) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        c_in = frames
        for _ in range(3):
            # ReLU is monotonic, so max-pool then ReLU equals ReLU then max-pool; pooling first
            # runs the ReLU (forward and backward) on a quarter of the values. Parameter names
            # are the same either way.
            act_pool = [nn.MaxPool2d(2), nn.ReLU()] if pool_first else [nn.ReLU(), nn.MaxPool2d(2)]
            layers += [nn.Conv2d(c_in, channels, 3, padding=1), *act_pool]
            c_in = channels
        self.features = nn.Sequential(*layers)
        side = size
        for _ in range(3):
            side //= 2
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(channels * side * side, hidden), nn.ReLU(),
                                  nn.Linear(hidden, n_actions))

    conv_dtype: torch.dtype | None = None
    """Lower precision for the conv trunk (``torch.bfloat16``: autocast, weights stay float32;
    the FC head and the Q-values stay float32); None: float32 throughout."""

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        batch = pixels.shape[:-3]
        x = pixels.reshape(-1, *pixels.shape[-3:]).to(torch.float32).div_(255.0)
        if self.conv_dtype is None:
            features = self.features(x)
        else:
            with torch.autocast(x.device.type, dtype=self.conv_dtype):
                features = self.features(x)
            features = features.float()
        return self.head(features).reshape(*batch, -1)


def make_q_actor(frames: int = 4, size: int = 84, pool_first: bool = True) -> QValueActor:
    """A TorchRL ``QValueActor`` reading ``pixels`` and writing ``action`` (int64 index),
    ``action_value`` and ``chosen_action_value``."""
    return QValueActor(QNetwork(frames, size, pool_first=pool_first), in_keys=["pixels"],
                       spec=Categorical(N_ACTIONS, dtype=torch.int64))
