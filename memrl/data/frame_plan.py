"""Where the frames of a write go in the frame ring of :mod:`memrl.data.frame_store`.

Everything here is vectorised torch on the data's device (no per-row Python loop, no copy to
the host). The pixel-heavy steps (row comparisons, ring gathers and scatters) go through
:class:`Pixels`, which uses numpy on CPU: a plain copy per frame and no thread pool, where
torch's index kernel is 10-100x slower for ``[n, 84, 84]`` uint8 rows (worst with 2 threads on
a busy 2-core machine).

Rows and streams: row ``r`` of a write of ``n`` rows belongs to stream ``r % S``; a write holds
whole steps (``n`` a multiple of ``S``), so consecutive writes keep the same rows per stream.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase


def ring_frames(max_size: int, stack: int = 4, streams: int = 1) -> int:
    """Frames a FIFO store of ``max_size`` env transitions from ``streams`` streams needs.

    ``2 max_size - 1 + (2 streams - 1) stack`` (``2 max_size + stack - 1`` for one stream):
    the bound of :mod:`memrl.data.frame_store`, tight.
    """
    return 2 * int(max_size) - 1 + (2 * int(streams) - 1) * int(stack)


@dataclass
class Pixels:
    """Pixel-heavy array steps, numpy on CPU (see the module docstring) and torch elsewhere.

    Args:
        numpy: use numpy (CPU tensors only).
    """

    numpy: bool

    def rows_equal(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """``[n]`` bool: row ``i`` of ``a`` equals row ``i`` of ``b`` (all elements)."""
        n = a.shape[0]
        if self.numpy:
            return torch.from_numpy((a.numpy() == b.numpy()).reshape(n, -1).all(1))
        return (a == b).reshape(n, -1).all(1)

    def frames_differ(self, pixels: torch.Tensor) -> torch.Tensor:
        """``[n, stack - 1]`` bool: frame ``j + 1`` of a stack differs from frame ``j``."""
        n, k = pixels.shape[0], pixels.shape[1] - 1
        if self.numpy:
            x = pixels.numpy()
            return torch.from_numpy((x[:, 1:] != x[:, :-1]).reshape(n, k, -1).any(2))
        return (pixels[:, 1:] != pixels[:, :-1]).reshape(n, k, -1).any(2)

    def gather(self, ring: torch.Tensor, slots: torch.Tensor) -> torch.Tensor:
        """``ring[slots]`` as a new contiguous tensor."""
        if self.numpy:
            return torch.from_numpy(ring.numpy()[slots.numpy()])
        return ring[slots]

    def scatter(self, ring: torch.Tensor, slots: torch.Tensor, frames: torch.Tensor,
                mask: torch.Tensor, count: int) -> None:
        """``ring[slots[mask]] = frames[mask]``; ``count`` is ``mask.sum()``, known on the host."""
        if self.numpy:
            m = mask.numpy()
            ring.numpy()[slots.numpy()[m]] = frames.numpy()[m]
            return
        # nonzero_static: the selected rows without a device-to-host sync for their count
        idx = torch.nonzero_static(mask.reshape(-1), size=count).reshape(-1)
        ring.index_copy_(0, slots.reshape(-1)[idx], frames.flatten(0, mask.ndim - 1)[idx])


@dataclass
class Plan:
    """Frame refs of the rows of a write and the frames it pushes (tensors on the data's device).

    Attributes:
        refs: ``[n, stack + 1]`` global frame counters: the ``stack`` frames of ``pixels``, then
            the newest frame of ``("next", "pixels")``.
        pushed: ``[n, stack + 1]`` bool: which of those frames this write pushes (frame ``j <
            stack`` is ``pixels[:, j]``, frame ``stack`` is ``next_pixels[:, -1]``).
        stats: ``[3]`` int64: frames pushed, the lowest ref of the write, rows whose next stack
            is not their stack shifted by one frame. One ``tolist()`` reads them (one sync).
    """

    refs: torch.Tensor
    pushed: torch.Tensor
    stats: torch.Tensor


def plan_write(pixels: torch.Tensor, next_pixels: torch.Tensor, head: int, streams: int,
               last: torch.Tensor, last_stack: torch.Tensor | None, valid: torch.Tensor | None,
               ops: Pixels) -> Plan:
    """Plan a write of ``n`` rows (``n`` a multiple of ``streams``) into a ring.

    Row ``r`` continues its stream (reuses refs, pushes only its new frame) when its stack
    equals the previous ``("next", "pixels")`` of stream ``r % streams``: row ``r - streams``
    of this write, or for the first ``streams`` rows, the stream's last stack before it.
    Otherwise its distinct consecutive frames are pushed (1 for a reset stack, at most
    ``stack``), then its new frame.

    Args:
        pixels, next_pixels: ``[n, stack, H, W]`` stacks.
        head: frames pushed so far (the counter of the next push).
        streams: interleaved streams ``S``.
        last: ``[S, stack]`` refs of each stream's last ``next`` stack (any value where unset).
        last_stack: ``[S, stack, H, W]`` their content; None when no stream has one.
        valid: ``[S]`` bool, streams whose ``last`` is set (None: all of them).
        ops: pixel backend.

    Returns:
        The :class:`Plan`.
    """
    n, stack = pixels.shape[0], pixels.shape[1]
    dev = pixels.device
    shifted = ops.rows_equal(next_pixels[:, :-1], pixels[:, 1:])
    cont = torch.zeros(n, dtype=torch.bool, device=dev)
    if n > streams:
        cont[streams:] = ops.rows_equal(pixels[streams:], next_pixels[:-streams])
    if last_stack is not None:
        first = ops.rows_equal(pixels[:streams], last_stack)
        cont[:streams] = first if valid is None else first & valid
    pushed = torch.ones((n, stack + 1), dtype=torch.bool, device=dev)
    pushed[:, 1:stack] = ops.frames_differ(pixels)
    pushed[:, :stack] &= ~cont[:, None]
    # counter of the last frame pushed at or before each position (row-major)
    ctr = pushed.reshape(-1).cumsum(0).reshape(n, stack + 1) + (head - 1)
    # refs: a continuation takes its stream's previous next stack, column by column from the
    # newest, so each column reads a column already final (rows r - S, or ``last``)
    ext = torch.zeros((streams + n, stack + 1), dtype=torch.long, device=dev)
    ext[:streams, 1:] = last
    ext[streams:, stack] = ctr[:, stack]
    for j in range(stack - 1, -1, -1):
        ext[streams:, j] = torch.where(cont, ext[:n, j + 1], ctr[:, j])
    refs = ext[streams:]
    stats = torch.stack([pushed.sum(), refs[:, 0].min(), (~shifted).sum()])
    return Plan(refs=refs, pushed=pushed, stats=stats)


def first_bad(pixels: torch.Tensor, next_pixels: torch.Tensor, ops: Pixels) -> int:
    """Index of the first row whose next stack is not its stack shifted by one frame."""
    ok = ops.rows_equal(next_pixels[:, :-1], pixels[:, 1:])
    return int(torch.nonzero(~ok)[0, 0])


def not_shifted_message(row: int) -> str:
    """The error for a row that CatFrames could not have made."""
    return (f"transition {row}: ('next', 'pixels') is not 'pixels' shifted by one frame (as "
            "CatFrames makes it): it cannot be stored compactly")


def count_frames(data: TensorDictBase, pixels_key: str = "pixels", chunk: int = 512,
                 streams: int = 1) -> int:
    """Frames that storing ``data`` (in order, into an empty store) pushes into the ring."""
    if len(data) % streams:
        raise ValueError(f"{len(data)} rows are not whole steps of {streams} streams")
    ops, head = Pixels(numpy=True), 0
    step = max(streams, chunk // streams * streams)
    last = torch.zeros((streams, data.get(pixels_key).shape[1]), dtype=torch.long)
    last_stack = None
    for start in range(0, len(data), step):
        part = data[start:start + step]
        p, q = part.get(pixels_key).cpu(), part.get(("next", pixels_key)).cpu()
        plan = plan_write(p, q, head, streams, last, last_stack, None, ops)
        pushes, _, bad = plan.stats.tolist()
        if bad:
            raise ValueError(not_shifted_message(start + first_bad(p, q, ops)))
        head += pushes
        last, last_stack = plan.refs[-streams:, 1:], q[-streams:]
    return head
