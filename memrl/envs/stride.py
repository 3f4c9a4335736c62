"""Strided frame stacks (``env.frame_stride``): which past frames an observation holds.

The stack at step t (t = 0 at reset) of S frames at stride k is the frames of steps
t - (S-1)k, ..., t - k, t, oldest first, with the reset frame standing in for every step
before 0 (TorchRL ``CatFrames``' ``padding="same"``). Every engine keeps the last
:func:`history_length` frames and shows the ones at :func:`stack_positions`.
"""

from __future__ import annotations

import numpy as np


def history_length(stack: int, stride: int) -> int:
    """Frames an engine keeps per observer: ``(stack - 1) * stride + 1`` (``stack`` at stride 1)."""
    return (stack - 1) * stride + 1


def stack_positions(stack: int, stride: int) -> list[int]:
    """Where the stacked frames lie in a history of :func:`history_length` frames, oldest first
    (the newest frame last): ``[0, k, 2k, ..., (S-1)k]``."""
    return [j * stride for j in range(stack)]


def select_frames(history: np.ndarray, channels: int, stride: int) -> np.ndarray:
    """The strided stack ``[S * C, H, W]`` of a history ``[L * C, H, W]`` (newest frame last) of
    frames of ``channels`` channels each; the history itself at stride 1."""
    if stride == 1:
        return history
    frames = history.reshape(-1, channels, *history.shape[1:])
    return np.ascontiguousarray(frames[::stride]).reshape(-1, *history.shape[1:])
