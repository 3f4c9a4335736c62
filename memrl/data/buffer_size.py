"""The bytes a training run's replay buffer will hold, checked against the machine's memory
before anything is allocated (``buffer.capacity=1000000000`` is refused in one line, naming the
bytes, instead of failing inside torch's allocator with a half-made run folder).

Imports no torch unless the buffer lives on a CUDA device.
"""

from __future__ import annotations

import os
from typing import Any

from memrl.errors import config_error

PIPELINE_STACK = 4
"""Frames per observation of the TorchRL pipeline (``memrl.envs.torchrl_env.make_env``)."""


def ring_frames(capacity: int, stack: int = PIPELINE_STACK, streams: int = 1, stride: int = 1) -> int:
    """Frames of the compact frame ring (:func:`memrl.data.frame_plan.ring_frames`, the same
    bound; restated here so that the start checks import no torch)."""
    d = (int(stack) - 1) * int(stride) + 1
    return 2 * int(capacity) - 1 + (2 * int(streams) - 1) * d


def buffer_bytes(cfg: Any) -> int:
    """Bytes of the frames the agent's replay buffer holds when full (uint8 grayscale frames of
    ``env.bev``: the frame ring with ``buffer.compact``, else both stacks of every transition);
    the smaller per-transition tensors (actions, rewards, refs) come on top."""
    frame = int(cfg.env.bev.width) * int(cfg.env.bev.height)
    capacity = int(cfg.buffer.capacity)
    if bool(cfg.buffer.compact):
        return frame * ring_frames(capacity, PIPELINE_STACK, int(cfg.env.num_envs), int(cfg.env.frame_stride))
    return frame * 2 * PIPELINE_STACK * capacity


def available_bytes() -> int | None:
    """Memory the machine can still give [bytes]: ``MemAvailable`` of ``/proc/meminfo``, else
    the free physical pages (``os.sysconf``); None where neither is known."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def cuda_free_bytes(device: str) -> int | None:
    """Free memory of a CUDA device [bytes] (None without CUDA)."""
    import torch

    if not torch.cuda.is_available():
        return None
    return int(torch.cuda.mem_get_info(torch.device(device))[0])


def check_buffer_fits(cfg: Any, available: int | None = None) -> None:
    """Refuse a replay buffer whose frames alone exceed the memory that is free where it lives
    (host memory, or the CUDA device's with ``device=cuda``), naming the bytes.

    Raises:
        ConfigError: ``config 'buffer.capacity': 1000000000 transitions need at least ...``.
    """
    need = buffer_bytes(cfg)
    device = str(cfg.get("device", "cpu"))
    where = "available memory"
    if available is None:
        cuda = cuda_free_bytes("cuda" if device == "auto" else device) \
            if device.startswith("cuda") or device == "auto" else None
        if cuda is not None:  # device=auto takes CUDA where present
            available, where = cuda, f"free memory on {'cuda' if device == 'auto' else device}"
        else:
            available = available_bytes()
    if available is None or need <= available:
        return
    raise config_error("buffer.capacity", f"{int(cfg.buffer.capacity)} transitions need at least "
                       f"{need:,} bytes ({need / 2**30:.1f} GiB) of frames, more than the "
                       f"{available:,} bytes ({available / 2**30:.1f} GiB) of {where}; "
                       "lower buffer.capacity")
