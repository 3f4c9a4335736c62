"""Compact replay storage: every 84x84 frame is held once, stacks are rebuilt at sampling.

A stored transition of the env pipeline holds two stacks of 4 uint8 frames, ``pixels`` and
``("next", "pixels")`` (56 KB at 84x84), which share 3 frames, and whose frames recur in the
3 transitions before and after. :class:`FrameStackStorage` is a TorchRL ``LazyTensorStorage``
that keeps, per transition, everything but the two stacks, plus ``frame_refs``: 5 global frame
counters (the 4 frames of ``pixels``, then the newest frame of ``("next", "pixels")``). The
frames themselves live once in a ring of ``ring_size`` frames (slot = counter % ring_size).
It plugs into any TorchRL buffer (``ReplayBuffer``, ``TensorDictReplayBuffer``, the online part
of ``OfflineToOnlineReplayBuffer``), samplers and writers unchanged, and keeps TorchRL's
``dumps``/``loads`` checkpointing (the ring is saved next to the per-transition part).

Streams. Data from ``S`` envs stepped together (``streams=S``) arrives as writes of whole
steps: row ``r`` of a write belongs to stream ``r % S`` (so a write of ``k S`` rows is ``k``
consecutive steps, step-major), and a write whose row count is not a multiple of ``S`` raises
``ValueError``. Writing a transition pushes frames into the ring:

- continuation (its ``pixels`` equal the previous ``("next", "pixels")`` of its stream, as
  consecutive env steps do; content is compared, so any data is stored right): the refs of
  that stack are reused, 1 push (the new frame);
- otherwise (an episode start, whose stack is the reset frame repeated by
  ``CatFrames(padding="same")``, or any stack): its distinct consecutive frames are pushed
  (1 for a reset stack, at most 4), plus the new frame.

Strided stacks (``stride`` k > 1, ``env.frame_stride``): a stack is ``[f(t-3k), f(t-2k),
f(t-k), f(t)]`` and consecutive stacks share no frame, so each stream keeps the refs of its last
``D = (stack - 1) k + 1`` frames and both stacks of a transition are read from them
(:mod:`memrl.data.stride_plan`; ``2 stack`` refs per transition). Pushes are as above: 1 per
continuation (its new frame), 2 for an episode start (the reset frame, standing for every
``f(s < 0)``, then the new frame), in row order. At k = 1, ``D = stack``.

Ring size bound (default ``2 max_size - 1 + (2 S - 1) D``; ``2 max_size + D - 1`` for one
stream). Env data pushes at most 2 frames per row (1 for a continuation, 2 for an episode
start). Count rows in write order; take a live row ``x`` of stream ``s``.

- Its oldest frame: if its episode started within its stack's span, the reset frame, first
  push of that start row, at or after row ``x - (D - 1) S``. Otherwise it is ``f(t - D + 1)``,
  the new frame of row ``x - D S`` (that stream's step ``t - D``), and rows ``x - (D - 1) S,
  ..., x`` of the same stream continue and push 1 frame each.
- With a FIFO writer, ``x`` is live after a write while at most ``max_size - 1`` rows follow
  it. From that oldest frame (excluded) to the end of such a write there are at most
  ``D S + max_size - 1`` rows, pushing at most ``2 (D S + max_size - 1) - D``.
- A frame with counter ``c`` is intact while ``c >= head - ring_size``, hence
  ``ring_size >= 2 max_size - 1 + (2 S - 1) D`` (episode start: ``>= 2 max_size``).

No fewer frames do: stream 0 continues for ``D + 1`` steps while every other row of the data
is a one-step episode (tested for 1, 3 and 16 streams at k = 1, 1 and 3 streams at k = 3).
At 84x84 and ``max_size`` 100,000 that is
200,003 frames = 1.41 GB for one stream and 200,123 for 16 (k = 3: 200,009 and 200,309),
against 5.6 GB for two full stacks per transition. A write that would overwrite a frame still
referenced (data that pushes more, e.g. shuffled mid-episode stacks, or a smaller ring) raises
:class:`FrameRingOverflow` before anything is changed.

Device. With ``device`` (any torch device) the ring and the per-transition tensors live there,
and writes and samples run there (:mod:`memrl.data.frame_plan`); pixels never go to the host.
Host syncs: a write reads 3 integers at once (frames pushed, lowest ref, shift check), plus 1
when the cached lower bound of the live refs falls below the ring's floor and is recomputed
(for env data whose episodes are much longer than one step, about once per ``max_size``
pushed frames; up to every write when nearly every row starts an episode); a sample reads 1
(its lowest ref). On CPU the pixel work uses numpy (see :class:`memrl.data.frame_plan.Pixels`).

TorchRL's own route, ``CatFrames.make_rb_transform_and_sampler`` + ``SliceSampler``, is not
used: it samples only slices of ``N`` steps lying inside one stored episode, so the first
``N - 1`` transitions of every episode are never sampled (measured: steps 0-2 of each episode
never come out, with or without ``strict_length``), it needs the whole FIFO buffer to be cut
into trajectories, and it stores each frame twice (as ``pixels`` and ``("next", "pixels")``).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase, is_tensor_collection

from memrl.data.frame_plan import (
    Pixels,
    count_frames,
    first_bad,
    not_shifted_message,
    plan_write,
    ring_frames,
)
from memrl.data.host_draw import HostDrawStorage
from memrl.data.stride_plan import not_strided_message, plan_strided

__all__ = ["REFS_KEY", "FrameRingOverflow", "FrameStackStorage", "count_frames", "ring_frames"]

REFS_KEY = "frame_refs"
"""Per-transition key of the global frame counters (``stack + 1`` of them, int64)."""


class FrameRingOverflow(RuntimeError):
    """A write would overwrite a frame that a live transition still refers to."""


def _slots(cursor: Any, n: int) -> torch.Tensor:
    """Storage rows written by ``set(cursor, ...)`` as a LongTensor of ``n`` indices."""
    if isinstance(cursor, slice):
        start, step = cursor.start or 0, cursor.step or 1
        return torch.arange(start, start + step * n, step)
    return torch.as_tensor(cursor, dtype=torch.long).reshape(-1)


class FrameStackStorage(HostDrawStorage):
    """``LazyTensorStorage`` of transitions whose stacked frames are stored once, in a ring.

    It takes and gives the usual transition layout (``pixels`` and ``("next", "pixels")``
    ``[stack, H, W]``); ``("next", "pixels")`` must be ``pixels`` shifted by one frame, as
    ``CatFrames`` makes it. See the module docstring for the layout, streams and the ring bound.

    Args:
        max_size: transitions held (at least ``streams``).
        frames: ring size in frames (default :func:`ring_frames`: enough for env data in FIFO
            order, whatever the episode lengths).
        stack: frames per stack.
        streams: interleaved env streams; row ``r`` of a write belongs to stream ``r % streams``
            and writes hold whole steps (a multiple of ``streams`` rows).
        device: where the ring, the per-transition tensors and samples live.
        pixels_key: the stacked key (its ``("next", key)`` twin is stored with it).
        chunk: rows compared at once when a large batch is written (bounds temporaries).
        numpy: pixel work with numpy (default: on CPU); False runs the torch path on CPU too.
        stride: frames between the stacked frames (``env.frame_stride`` k; stacks ``[f(t-3k),
            f(t-2k), f(t-k), f(t)]``): k > 1 stores ``2 stack`` refs per transition
            (:mod:`memrl.data.stride_plan`).
    """

    def __init__(self, max_size: int, *, frames: int | None = None, stack: int = 4,
                 streams: int = 1, device: torch.device | str = "cpu",
                 pixels_key: str = "pixels", chunk: int = 512, numpy: bool | None = None,
                 stride: int = 1) -> None:
        super().__init__(max_size, device=device)
        self.stack, self.streams, self.stride = int(stack), int(streams), int(stride)
        if self.stride < 1:
            raise ValueError(f"stride must be >= 1, got {stride}")
        if self.streams < 1 or self.max_size < self.streams:
            raise ValueError(f"streams must be in [1, max_size={max_size}], got {streams}")
        self.ring_size = (int(frames) if frames is not None
                          else ring_frames(max_size, stack, self.streams, self.stride))
        if self.ring_size < self.stack + 1:
            raise ValueError(f"a frame ring needs at least {self.stack + 1} frames")
        self.pixels_key = pixels_key
        self.chunk = int(chunk)
        self._dev = torch.device(self.device)
        self._ops = Pixels(numpy=self._dev.type == "cpu" if numpy is None else bool(numpy))
        self._ring: torch.Tensor | None = None
        self._ring_a: Any = None  # the ring as a backend array (same memory)
        self._head = 0  # frames pushed so far
        # refs of each stream's last ``next`` stack and their slots (backend arrays), None
        # before the first write: whole-step writes give every stream one at once
        self._last: Any = None
        self._last_slots: Any = None
        self._live_lb: float = math.inf  # a lower bound of the refs of live transitions
        self._hist: torch.Tensor | None = None  # stride > 1: [S, span] refs of recent frames

    # ------------------------------------------------------------------ write
    def set(self, cursor: Any, data: Any, *, set_cursor: bool = True) -> None:  # type: ignore[override]
        if not is_tensor_collection(data):
            raise TypeError(f"{type(self).__name__} stores TensorDicts, got {type(data)}")
        if data.batch_dims == 0:  # a single transition (ReplayBuffer.add)
            data = data.unsqueeze(0)
            cursor = torch.as_tensor([int(cursor)])
        n = data.shape[0]
        if n % self.streams:
            raise ValueError(f"a write of {n} rows is not whole steps of {self.streams} streams "
                             f"(row r belongs to stream r % {self.streams})")
        slots = _slots(cursor, n)
        step = max(self.streams, min(self.chunk, self.max_size) // self.streams * self.streams)
        if n > step:  # bounded temporaries, and no row written twice within one part
            for start in range(0, n, step):
                self.set(slots[start:start + step], data[start:start + step],
                         set_cursor=set_cursor)
            return
        super().set(slots, self._compact(data, slots), set_cursor=set_cursor)

    def _compact(self, data: TensorDictBase, slots: torch.Tensor) -> TensorDictBase:
        key, nkey = self.pixels_key, ("next", self.pixels_key)
        pixels, next_pixels = data.get(key), data.get(nkey)
        if pixels.ndim != 4 or pixels.shape[1] != self.stack:
            raise ValueError(f"{key!r} must be [n, {self.stack}, H, W], got {tuple(pixels.shape)}")
        if next_pixels.shape != pixels.shape:
            raise ValueError(f"pixels {tuple(pixels.shape)} and next pixels "
                             f"{tuple(next_pixels.shape)} differ in shape")
        if self.stride > 1:
            return self._compact_strided(data, slots)
        ops, n = self._ops, len(pixels)
        p, q = ops.arr(pixels.to(self._dev)), ops.arr(next_pixels.to(self._dev))
        last_stack = None
        if self._last is not None and self._ring_a is not None:
            last_stack = self._ring_a[self._last_slots]
        plan = plan_write(p, q, self._head, self.streams, self._last, last_stack, ops,
                          self.ring_size)
        pushes, new_min, bad = plan.read_stats()  # the write's one sync
        if bad:
            raise ValueError(not_shifted_message(first_bad(p, q, ops)))
        head = self._head + pushes
        self._check_live(new_min, n, slots, head)
        if self._ring is None:
            # Touched now (zero_), so the resident size is the bound from the first write on.
            self._set_ring(torch.empty((self.ring_size, *pixels.shape[-2:]), dtype=pixels.dtype,
                                       device=self._dev).zero_())
        if ops.numpy:  # the two sources, without a concatenated copy
            ops.scatter(self._ring_a, plan.slots[:, :-1], p, plan.pushed[:, :-1], pushes - n)
            ops.scatter(self._ring_a, plan.slots[:, -1:], q[:, -1:], plan.pushed[:, -1:], n)
        else:  # one index_copy_ (a kernel launch matters more than a small copy)
            ops.scatter(self._ring_a, plan.slots, torch.cat([p, q[:, -1:]], 1), plan.pushed,
                        pushes)
        self._head = head
        # views of the fresh plan arrays, never written again
        self._last, self._last_slots = plan.refs[-self.streams:, 1:], plan.slots[-self.streams:, 1:]
        # on the storage device already (TensorDict writes a device-less batch slower)
        out = data.exclude(key, nkey).to(self._dev)
        out.set(REFS_KEY, ops.tensor(plan.refs))
        return out

    def _compact_strided(self, data: TensorDictBase, slots: torch.Tensor) -> TensorDictBase:
        """:meth:`_compact` for strided stacks (:mod:`memrl.data.stride_plan`)."""
        key, nkey = self.pixels_key, ("next", self.pixels_key)
        p, q = data.get(key).to(self._dev), data.get(nkey).to(self._dev)
        hist_frames = None
        if self._hist is not None:
            hist_frames = (self._ring[self._hist.clamp(min=0) % self.ring_size]
                           if self._ring is not None else
                           torch.zeros((*self._hist.shape, *p.shape[2:]), dtype=p.dtype,
                                       device=self._dev))
        plan = plan_strided(p, q, self._head, self.streams, self.stride, self._hist, hist_frames)
        if plan.bad >= 0:
            raise ValueError(not_strided_message(plan.bad, self.stride))
        head = self._head + len(plan.pushed_refs)
        self._check_live(int(plan.refs.min()), len(p), slots, head)
        if self._ring is None:
            self._set_ring(torch.empty((self.ring_size, *p.shape[-2:]), dtype=p.dtype,
                                       device=self._dev).zero_())
        assert self._ring is not None
        self._ring.index_copy_(0, plan.pushed_refs.to(self._dev) % self.ring_size, plan.pushed)
        self._head, self._hist = head, plan.hist
        out = data.exclude(key, nkey).to(self._dev)
        out.set(REFS_KEY, plan.refs)
        return out

    def _set_ring(self, ring: torch.Tensor | None) -> None:
        self._ring = ring
        self._ring_a = None if ring is None else self._ops.arr(ring)

    def _check_live(self, new_min: int, n: int, slots: torch.Tensor, head: int) -> None:
        """Raise unless every transition live after this write keeps its frames."""
        floor = head - self.ring_size  # frames with a lower counter are overwritten
        if new_min < floor:
            raise FrameRingOverflow(
                f"a write of {n} transitions pushes more frames than the ring of "
                f"{self.ring_size} holds; use a larger `frames`")
        if floor > self._live_lb and self.initialized and len(self) > 0:
            size = len(self)
            keep = torch.ones(size, dtype=torch.bool)
            keep[slots[slots < size]] = False  # rows overwritten by this write
            old = self._storage.get(REFS_KEY)[:size, 0]
            exact = (int(torch.where(keep.to(old.device), old, old.new_tensor(2**62)).min())
                     if keep.any() else math.inf)
            if exact < floor:
                need = ring_frames(self.max_size, self.stack, self.streams, self.stride)
                raise FrameRingOverflow(
                    f"the frame ring ({self.ring_size} frames) is too small: this write would "
                    f"overwrite frames of live transitions (needs >= {need} for env data of "
                    f"{self.streams} stream(s) in FIFO order)")
            self._live_lb = exact
        self._live_lb = min(self._live_lb, new_min)

    # ------------------------------------------------------------------ read
    def get(self, index: Any) -> Any:
        td = super().get(index)
        refs = td.get(REFS_KEY)
        if refs.numel() and int(refs.min()) < self._head - self.ring_size:
            raise FrameRingOverflow("a stored transition lost its frames (ring overwritten)")
        assert self._ring_a is not None
        # Two contiguous gathers, not two views of one: the stacks must not share memory.
        ops, slots = self._ops, self._ops.arr(refs % self.ring_size)
        out = td.exclude(REFS_KEY)
        out.set(self.pixels_key, ops.tensor(self._ring_a[slots[..., : self.stack]]))
        nxt = slots[..., self.stack:] if self.stride > 1 else slots[..., 1:]
        out.set(("next", self.pixels_key), ops.tensor(self._ring_a[nxt]))
        return out

    def _empty(self) -> None:
        super()._empty()
        self._head, self._live_lb, self._last, self._last_slots = 0, math.inf, None, None
        self._hist = None

    @property
    def frames_used(self) -> int:
        """Ring slots written so far."""
        return min(self._head, self.ring_size)

    def nbytes(self) -> int:
        """Bytes held: the ring plus the per-transition tensors."""
        ring = self._ring.numel() * self._ring.element_size() if self._ring is not None else 0
        rows = self._storage.bytes() if self.initialized else 0
        return int(ring + rows)

    # ------------------------------------------------------------------ checkpoints
    def _frame_meta(self) -> dict[str, Any]:
        rows = None if self._last is None else self._ops.tensor(self._last).tolist()
        # one stream keeps the original layout (a list or None), so old checkpoints still load
        last = rows[0] if rows is not None and self.streams == 1 else rows
        meta = {"head": self._head, "last": last, "live_lb": self._live_lb,
                "ring_size": self.ring_size, "stack": self.stack, "streams": self.streams}
        if self.stride > 1:  # k = 1 keeps the original layout
            meta.update(stride=self.stride,
                        hist=None if self._hist is None else self._hist.cpu().tolist())
        return meta

    def _set_frame_meta(self, meta: dict[str, Any], ring: Any) -> None:
        streams, stride = int(meta.get("streams", 1)), int(meta.get("stride", 1))
        if (int(meta["ring_size"]) != self.ring_size or int(meta["stack"]) != self.stack
                or streams != self.streams or stride != self.stride):
            raise ValueError(f"frame ring of {meta['ring_size']} frames x stack {meta['stack']} "
                             f"x {streams} stream(s) x stride {stride} cannot load into "
                             f"{self.ring_size} x {self.stack} x {self.streams} x stride "
                             f"{self.stride}")
        hist = meta.get("hist")
        self._hist = None if hist is None else torch.tensor(hist, dtype=torch.long,
                                                            device=self._dev)
        self._head = int(meta["head"])
        self._live_lb = float(meta["live_lb"])
        last = meta["last"]
        if last is None:
            self._last = self._last_slots = None
        else:
            rows = [last] if self.streams == 1 else last
            self._last = self._ops.arr(torch.tensor(rows, dtype=torch.long, device=self._dev))
            self._last_slots = self._last % self.ring_size
        if ring is None:
            self._set_ring(None)
            return
        ring_t = ring if isinstance(ring, torch.Tensor) else torch.from_numpy(np.array(ring))
        self._set_ring(torch.empty((self.ring_size, *ring_t.shape[1:]), dtype=ring_t.dtype,
                                   device=self._dev).zero_())
        assert self._ring is not None
        self._ring[: len(ring_t)] = ring_t.to(self._dev)

    def state_dict(self) -> dict[str, Any]:
        state = super().state_dict()
        ring = self._ring[: self.frames_used] if self._ring is not None else None
        state["frame_ring"] = {"meta": self._frame_meta(), "ring": ring}
        return state

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        super().load_state_dict(state_dict)
        storage: Any = self._storage  # type: ignore[has-type]  # TorchRL leaves it untyped
        if storage is not None:  # TorchRL builds a fresh storage on the CPU
            self._storage = storage.to(self._dev)
        self._set_frame_meta(state_dict["frame_ring"]["meta"], state_dict["frame_ring"]["ring"])

    def dumps(self, path: str | Path) -> None:
        """TorchRL's storage checkpoint (per-transition part) plus the used part of the ring."""
        super().dumps(path)
        path = Path(path)
        torch.save(self._frame_meta(), path / "frame_ring_meta.pt")
        if self._ring is not None:
            np.save(path / "frame_ring.npy", self._ring[: self.frames_used].cpu().numpy())

    def loads(self, path: str | Path) -> None:
        super().loads(path)
        path = Path(path)
        ring_file = path / "frame_ring.npy"
        ring = np.load(ring_file, mmap_mode="r") if ring_file.exists() else None
        self._set_frame_meta(torch.load(path / "frame_ring_meta.pt"), ring)
