"""Where the frames of a write go in the frame ring of :mod:`memrl.data.frame_store`.

Everything here is vectorised (no per-row Python loop) on the data's device (no copy to the
host), written once for two array backends (:class:`Pixels`): torch, and on CPU numpy, for its
plain copy per frame without a thread pool where torch's index kernel is 10-100x slower for
``[n, 84, 84]`` uint8 rows (worst with 2 threads on a busy 2-core machine), and for its lower
per-call overhead on the small integer arrays of a one-step write.

Rows and streams: row ``r`` of a write of ``n`` rows belongs to stream ``r % S``; a write holds
whole steps (``n`` a multiple of ``S``), so consecutive writes keep the same rows per stream.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase

from memrl.data.stride_plan import count_strided


def ring_frames(max_size: int, stack: int = 4, streams: int = 1, stride: int = 1) -> int:
    """Frames a FIFO store of ``max_size`` env transitions from ``streams`` streams needs.

    ``2 max_size - 1 + (2 streams - 1) D`` with ``D = (stack - 1) stride + 1`` the frames a
    stack spans (``D = stack`` at stride 1; ``2 max_size + D - 1`` for one stream): the bound
    of :mod:`memrl.data.frame_store`, tight.
    """
    d = (int(stack) - 1) * int(stride) + 1
    return 2 * int(max_size) - 1 + (2 * int(streams) - 1) * d


@dataclass
class Pixels:
    """Array backend of the frame ring: numpy on CPU (see the module docstring), torch elsewhere.

    Plans and ring work take and give the backend's arrays (numpy arrays or torch tensors,
    through the methods both share); :meth:`arr` and :meth:`tensor` convert, zero-copy.

    Args:
        numpy: use numpy (CPU tensors only).
    """

    numpy: bool

    def arr(self, t: torch.Tensor) -> Any:
        """The backend's array sharing ``t``'s memory."""
        return t.numpy() if self.numpy else t

    def tensor(self, a: Any) -> torch.Tensor:
        """The torch tensor sharing ``a``'s memory."""
        return torch.from_numpy(a) if self.numpy else a

    def where(self, cond: Any, a: Any, b: Any) -> Any:
        return np.where(cond, a, b) if self.numpy else torch.where(cond, a, b)

    def zeros(self, shape: tuple[int, ...], like: Any, boolean: bool = False) -> Any:
        """Zeros on ``like``'s device, bool or int64."""
        if self.numpy:
            return np.zeros(shape, dtype=bool if boolean else np.int64)
        return torch.zeros(shape, dtype=torch.bool if boolean else torch.long, device=like.device)

    @staticmethod
    def rows_equal(a: Any, b: Any) -> Any:
        """``[n]`` bool: row ``i`` of ``a`` equals row ``i`` of ``b`` (all elements)."""
        return (a == b).reshape(a.shape[0], -1).all(1)

    def scatter(self, ring: Any, slots: Any, frames: Any, mask: Any, count: int) -> None:
        """``ring[slots[mask]] = frames[mask]``; ``count`` is ``mask.sum()``, known on the host."""
        if self.numpy:
            ring[slots[mask]] = frames[mask]
            return
        # nonzero_static: the selected rows without a device-to-host sync for their count
        idx = torch.nonzero_static(mask.reshape(-1), size=count).reshape(-1)
        ring.index_copy_(0, slots.reshape(-1)[idx], frames.flatten(0, mask.ndim - 1)[idx])


@dataclass
class Plan:
    """Frame refs of the rows of a write and the frames it pushes (backend arrays).

    Attributes:
        refs: ``[n, stack + 1]`` int64 global frame counters: the ``stack`` frames of
            ``pixels``, then the newest frame of ``("next", "pixels")``.
        slots: ``refs % ring_size``, their ring slots.
        pushed: ``[n, stack + 1]`` bool: which of those frames this write pushes (frame ``j <
            stack`` is ``pixels[:, j]``, frame ``stack`` is ``next_pixels[:, -1]``).
        stats: frames pushed, the lowest ref of the write, rows whose next stack is not their
            stack shifted by one frame: ints (numpy) or a ``[3]`` tensor on the device.
    """

    refs: Any
    slots: Any
    pushed: Any
    stats: torch.Tensor | list[int]

    def read_stats(self) -> list[int]:
        """:attr:`stats` on the host: one device-to-host sync on a device."""
        return self.stats.tolist() if isinstance(self.stats, torch.Tensor) else self.stats


def plan_write(p: Any, q: Any, head: int, streams: int, last: Any | None, last_stack: Any | None,
               ops: Pixels, ring_size: int = 1) -> Plan:
    """Plan a write of ``n`` rows (``n`` a multiple of ``streams``) into a ring.

    Row ``r`` continues its stream (reuses refs, pushes only its new frame) when its stack
    equals the previous ``("next", "pixels")`` of stream ``r % streams``: row ``r - streams``
    of this write, or for the first ``streams`` rows, the stream's last stack before it.
    Otherwise its distinct consecutive frames are pushed (1 for a reset stack, at most
    ``stack``), then its new frame.

    Args:
        p, q: ``pixels`` and ``("next", "pixels")``, ``[n, stack, H, W]`` backend arrays.
        head: frames pushed so far (the counter of the next push).
        streams: interleaved streams ``S``.
        last: ``[S, stack]`` refs of each stream's last ``next`` stack; None before the first
            write.
        last_stack: ``[S, stack, H, W]`` their content; None before the first write.
        ops: array backend.
        ring_size: frames in the ring (for :attr:`Plan.slots`).

    Returns:
        The :class:`Plan`.
    """
    n, stack = p.shape[0], p.shape[1]
    shifted = ops.rows_equal(q[:, :-1], p[:, 1:])
    cont = ops.zeros((n,), p, boolean=True)
    if n > streams:
        cont[streams:] = ops.rows_equal(p[streams:], q[:-streams])
    if last_stack is not None:
        cont[:streams] = ops.rows_equal(p[:streams], last_stack)
    if last is None:
        last = ops.zeros((streams, stack), p)
    pushed = ops.zeros((n, stack + 1), p, boolean=True)
    pushed[:, 0] = pushed[:, stack] = True
    pushed[:, 1:stack] = (p[:, 1:] != p[:, :-1]).reshape(n, stack - 1, -1).any(2)
    pushed[:, :stack] &= ~cont[:, None]
    # counter of the last frame pushed at or before each position (row-major)
    ctr = pushed.reshape(-1).cumsum(0).reshape(n, stack + 1) + (head - 1)
    # refs: a continuation takes its stream's previous next stack (row r - S, or ``last``)
    if n == streams:  # one step: every previous next stack is in ``last``
        refs = ctr
        refs[:, :stack] = ops.where(cont[:, None], last, ctr[:, :stack])
    else:  # column by column from the newest, so each reads a column already final
        ext = ops.zeros((streams + n, stack + 1), p)
        ext[:streams, 1:] = last
        ext[streams:, stack] = ctr[:, stack]
        for j in range(stack - 1, -1, -1):
            ext[streams:, j] = ops.where(cont, ext[:n, j + 1], ctr[:, j])
        refs = ext[streams:]
    stats: torch.Tensor | list[int]
    if ops.numpy:
        stats = [int(pushed.sum()), int(refs[:, 0].min()), int((~shifted).sum())]
    else:
        stats = torch.stack([pushed.sum(), refs[:, 0].min(), (~shifted).sum()])
    return Plan(refs=refs, slots=refs % ring_size, pushed=pushed, stats=stats)


def first_bad(p: Any, q: Any, ops: Pixels) -> int:
    """Index of the first row whose next stack is not its stack shifted by one frame."""
    ok = ops.tensor(ops.rows_equal(q[:, :-1], p[:, 1:]))
    return int(torch.nonzero(~ok)[0, 0])


def not_shifted_message(row: int) -> str:
    """The error for a row that CatFrames could not have made."""
    return (f"transition {row}: ('next', 'pixels') is not 'pixels' shifted by one frame (as "
            "CatFrames makes it): it cannot be stored compactly")


def count_frames(data: TensorDictBase, pixels_key: str = "pixels", chunk: int = 512,
                 streams: int = 1, stride: int = 1) -> int:
    """Frames that storing ``data`` (in order, into an empty store) pushes into the ring
    (``stride`` frames between the stacked frames)."""
    if stride != 1:
        return count_strided(data, pixels_key, streams, stride)
    if len(data) % streams:
        raise ValueError(f"{len(data)} rows are not whole steps of {streams} streams")
    ops, head = Pixels(numpy=True), 0
    step = max(streams, chunk // streams * streams)
    last = np.zeros((streams, data.get(pixels_key).shape[1]), dtype=np.int64)
    last_stack = None
    for start in range(0, len(data), step):
        part = data[start:start + step]
        p, q = part.get(pixels_key).cpu().numpy(), part.get(("next", pixels_key)).cpu().numpy()
        plan = plan_write(p, q, head, streams, last, last_stack, ops)
        pushes, _, bad = plan.read_stats()
        if bad:
            raise ValueError(not_shifted_message(start + first_bad(p, q, ops)))
        head += pushes
        last, last_stack = plan.refs[-streams:, 1:], q[-streams:]
    return head
