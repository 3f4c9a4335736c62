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

Writing a transition pushes frames into the ring:

- continuation (its ``pixels`` equal the previous transition's ``("next", "pixels")``, as
  consecutive env steps do): the refs of that stack are reused, 1 push (the new frame);
- otherwise (an episode start, whose stack is the reset frame repeated by
  ``CatFrames(padding="same")``, or any stack): its distinct consecutive frames are pushed
  (1 for a reset stack, at most 4), plus the new frame.

Ring size bound (default ``2 * max_size + stack - 1``). Env data pushes at most 2 frames per
transition: 1 for a continuation, 2 for an episode start (the reset frame and the new frame).
Let transition ``t`` be written when ``h0`` frames have been pushed, pushing ``k`` frames.

- Its oldest frame: a continuation reuses the previous ``next`` stack, whose at most
  ``stack`` distinct frames were the last ``stack`` pushes, so its oldest counter is
  ``>= h0 - stack`` (and ``k = 1``); an episode start's oldest counter is ``h0`` (``k = 2``).
- With a FIFO writer, ``t`` is live while at most ``max_size - 1`` later transitions are
  written, pushing at most ``2 (max_size - 1)``: the head stays ``<= h0 + k + 2 max_size - 2``.
- A frame with counter ``c`` is intact while ``c >= head - ring_size``. Continuation:
  ``h0 - stack >= h0 + 2 max_size - 1 - ring_size`` iff ``ring_size >= 2 max_size + stack - 1``;
  episode start: ``ring_size >= 2 max_size``.

So ``2 * max_size + stack - 1`` frames suffice whatever the episode lengths, and no fewer do
(a continuation followed by ``max_size - 1`` one-step episodes; both tested). At 84x84 and
``max_size`` 100,000 that is 200,003 frames = 1.41 GB, against 5.6 GB for two full stacks
per transition. A write that would overwrite a frame still referenced (data that pushes more,
e.g. shuffled mid-episode stacks, or a smaller ring) raises :class:`FrameRingOverflow` before
anything is changed.

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
from torchrl.data import LazyTensorStorage

REFS_KEY = "frame_refs"
"""Per-transition key of the global frame counters (``stack + 1`` of them, int64)."""


class FrameRingOverflow(RuntimeError):
    """A write would overwrite a frame that a live transition still refers to."""


def ring_frames(max_size: int, stack: int = 4) -> int:
    """Frames a FIFO store of ``max_size`` env transitions needs (see the module docstring)."""
    return 2 * int(max_size) + int(stack) - 1


def _slots(cursor: Any, n: int) -> torch.Tensor:
    """Storage rows written by ``set(cursor, ...)`` as a LongTensor of ``n`` indices."""
    if isinstance(cursor, slice):
        start, step = cursor.start or 0, cursor.step or 1
        return torch.arange(start, start + step * n, step)
    return torch.as_tensor(cursor, dtype=torch.long).reshape(-1)


def plan_pushes(pixels: np.ndarray, next_pixels: np.ndarray, head: int,
                prev_refs: list[int] | None, prev_stack: np.ndarray | None
                ) -> tuple[list[list[int]], list[tuple[int, int, int]], list[int] | None]:
    """Frame refs of ``n`` transitions and the frames to push for them (numpy: no thread pool).

    Args:
        pixels, next_pixels: ``[n, stack, H, W]`` stacks.
        head: frames pushed so far (the counter of the next push).
        prev_refs: refs of the ``next`` stack of the transition written last (None: none).
        prev_stack: that stack's content ``[stack, H, W]``.

    Returns:
        ``refs`` (``n`` lists of ``stack + 1`` counters), ``pushes`` as (counter, row, frame)
        with frame in ``[0, stack)`` for ``pixels[row, frame]`` and ``stack`` for
        ``next_pixels[row, -1]``, and the refs of the last row's ``next`` stack.
    """
    n, stack = pixels.shape[0], pixels.shape[1]
    if next_pixels.shape != pixels.shape:
        raise ValueError(f"pixels {tuple(pixels.shape)} and next pixels "
                         f"{tuple(next_pixels.shape)} differ in shape")
    shifted = (next_pixels[:, :-1] == pixels[:, 1:]).reshape(n, -1).all(1)
    if not shifted.all():
        row = int(np.flatnonzero(~shifted)[0])
        raise ValueError(f"transition {row}: ('next', 'pixels') is not 'pixels' shifted by one "
                         "frame (as CatFrames makes it): it cannot be stored compactly")
    cont = np.zeros(n, dtype=bool)
    if n > 1:
        cont[1:] = (pixels[1:] == next_pixels[:-1]).reshape(n - 1, -1).all(1)
    if prev_refs is not None and prev_stack is not None:
        cont[0] = np.array_equal(pixels[0], prev_stack)
    # new[i][j - 1]: frame j of row i differs from frame j - 1 (only needed where not cont)
    new = (pixels[:, 1:] != pixels[:, :-1]).reshape(n, stack - 1, -1).any(2).tolist()
    refs: list[list[int]] = []
    pushes: list[tuple[int, int, int]] = []
    prev = prev_refs
    for i, continues in enumerate(cont.tolist()):
        if continues:
            assert prev is not None
            p = list(prev)
        else:
            p, c = [], head
            for j in range(stack):
                if j == 0 or new[i][j - 1]:
                    c = head
                    pushes.append((head, i, j))
                    head += 1
                p.append(c)
        pushes.append((head, i, stack))
        refs.append(p + [head])
        head += 1
        prev = p[1:] + [refs[-1][-1]]
    return refs, pushes, prev


def count_frames(data: TensorDictBase, pixels_key: str = "pixels", chunk: int = 512) -> int:
    """Frames that storing ``data`` (in order, into an empty store) pushes into the ring."""
    head, prev_refs, prev_stack = 0, None, None
    for start in range(0, len(data), chunk):
        part = data[start:start + chunk]
        p, q = part.get(pixels_key).numpy(), part.get(("next", pixels_key)).numpy()
        refs, pushes, prev_refs = plan_pushes(p, q, head, prev_refs, prev_stack)
        head += len(pushes)
        prev_stack = q[-1]
    return head


class FrameStackStorage(LazyTensorStorage):
    """``LazyTensorStorage`` of transitions whose stacked frames are stored once, in a ring.

    It takes and gives the usual transition layout (``pixels`` and ``("next", "pixels")``
    ``[stack, H, W]``); ``("next", "pixels")`` must be ``pixels`` shifted by one frame, as
    ``CatFrames`` makes it. See the module docstring for the layout and the ring-size bound.

    Args:
        max_size: transitions held.
        frames: ring size in frames (default :func:`ring_frames`: enough for env data in FIFO
            order, whatever the episode lengths).
        stack: frames per stack.
        pixels_key: the stacked key (its ``("next", key)`` twin is stored with it).
        chunk: rows compared at once when a large batch is written (bounds temporaries).
    """

    def __init__(self, max_size: int, *, frames: int | None = None, stack: int = 4,
                 pixels_key: str = "pixels", chunk: int = 512) -> None:
        super().__init__(max_size)
        self.stack = int(stack)
        self.ring_size = int(frames) if frames is not None else ring_frames(max_size, stack)
        if self.ring_size < self.stack + 1:
            raise ValueError(f"a frame ring needs at least {self.stack + 1} frames")
        self.pixels_key = pixels_key
        self.chunk = int(chunk)
        self._ring: torch.Tensor | None = None
        self._head = 0  # frames pushed so far
        self._last: list[int] | None = None  # refs of the last written ``next`` stack
        self._live_lb: float = math.inf  # a lower bound of the refs of live transitions

    # ------------------------------------------------------------------ write
    def set(self, cursor: Any, data: Any, *, set_cursor: bool = True) -> None:  # type: ignore[override]
        if not is_tensor_collection(data):
            raise TypeError(f"{type(self).__name__} stores TensorDicts, got {type(data)}")
        if data.batch_dims == 0:  # a single transition (ReplayBuffer.add)
            data = data.unsqueeze(0)
            cursor = torch.as_tensor([int(cursor)])
        n = data.shape[0]
        slots = _slots(cursor, n)
        step = min(self.chunk, self.max_size)
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
        p_np, q_np = pixels.numpy(), next_pixels.numpy()
        prev_stack = None
        if self._last is not None and self._ring is not None:
            prev_stack = self._ring.numpy()[np.asarray(self._last) % self.ring_size]
        refs, pushes, last = plan_pushes(p_np, q_np, self._head, self._last, prev_stack)
        head = self._head + len(pushes)
        ref_t = torch.tensor(refs, dtype=torch.long)
        self._check_live(ref_t, slots, head)
        if self._ring is None:
            # Touched now (zero_), so the resident size is the bound from the first write on.
            self._ring = torch.empty((self.ring_size, *pixels.shape[-2:]),
                                     dtype=pixels.dtype).zero_()
        ring = self._ring.numpy()
        ctr, rows, cols = (np.asarray(x) for x in zip(*pushes, strict=True))
        from_p, from_q = cols < self.stack, cols == self.stack
        ring[ctr[from_p] % self.ring_size] = p_np[rows[from_p], cols[from_p]]
        ring[ctr[from_q] % self.ring_size] = q_np[rows[from_q], -1]
        self._head, self._last = head, last
        out = data.exclude(key, nkey)
        out.set(REFS_KEY, ref_t)
        return out

    def _check_live(self, refs: torch.Tensor, slots: torch.Tensor, head: int) -> None:
        """Raise unless every transition live after this write keeps its frames."""
        floor = head - self.ring_size  # frames with a lower counter are overwritten
        new_min = int(refs[:, 0].min())  # refs grow along a row: column 0 is the oldest
        if new_min < floor:
            raise FrameRingOverflow(
                f"a write of {len(refs)} transitions pushes more frames than the ring of "
                f"{self.ring_size} holds; use a larger `frames`")
        if floor > self._live_lb and self.initialized and len(self) > 0:
            size = len(self)
            keep = torch.ones(size, dtype=torch.bool)
            keep[slots[slots < size]] = False  # rows overwritten by this write
            old = self._storage.get(REFS_KEY)[:size, 0][keep]
            exact = int(old.min()) if len(old) else math.inf
            if exact < floor:
                need = ring_frames(self.max_size, self.stack)
                raise FrameRingOverflow(
                    f"the frame ring ({self.ring_size} frames) is too small: this write would "
                    f"overwrite frames of live transitions (needs >= {need} for env data in "
                    "FIFO order)")
            self._live_lb = exact
        self._live_lb = min(self._live_lb, new_min)

    # ------------------------------------------------------------------ read
    def get(self, index: Any) -> Any:
        td = super().get(index)
        refs = td.get(REFS_KEY)
        if refs.numel() and int(refs.min()) < self._head - self.ring_size:
            raise FrameRingOverflow("a stored transition lost its frames (ring overwritten)")
        assert self._ring is not None
        # numpy's gather: a plain copy per frame, no thread pool (torch's index kernel is 10-100x
        # slower here for [n, 84, 84] uint8 rows, worst with 2 threads on a busy 2-core machine).
        # Two contiguous gathers, not two views of one: the stacks must not share memory.
        ring, slots = self._ring.numpy(), (refs % self.ring_size).numpy()
        out = td.exclude(REFS_KEY)
        out.set(self.pixels_key, torch.from_numpy(ring[slots[..., : self.stack]]))
        out.set(("next", self.pixels_key), torch.from_numpy(ring[slots[..., 1:]]))
        return out

    def _empty(self) -> None:
        super()._empty()
        self._head, self._last, self._live_lb = 0, None, math.inf

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
        return {"head": self._head, "last": self._last, "live_lb": self._live_lb,
                "ring_size": self.ring_size, "stack": self.stack}

    def _set_frame_meta(self, meta: dict[str, Any], ring: Any) -> None:
        if int(meta["ring_size"]) != self.ring_size or int(meta["stack"]) != self.stack:
            raise ValueError(f"frame ring of {meta['ring_size']} frames x stack {meta['stack']} "
                             f"cannot load into {self.ring_size} x {self.stack}")
        self._head, self._last = int(meta["head"]), meta["last"]
        self._live_lb = float(meta["live_lb"])
        if ring is None:
            self._ring = None
            return
        dtype = (ring.dtype if isinstance(ring, torch.Tensor)
                 else torch.from_numpy(np.empty(0, ring.dtype)).dtype)
        self._ring = torch.empty((self.ring_size, *ring.shape[1:]), dtype=dtype).zero_()
        self._ring.numpy()[: len(ring)] = ring.numpy() if isinstance(ring, torch.Tensor) else ring

    def state_dict(self) -> dict[str, Any]:
        state = super().state_dict()
        ring = self._ring[: self.frames_used] if self._ring is not None else None
        state["frame_ring"] = {"meta": self._frame_meta(), "ring": ring}
        return state

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        super().load_state_dict(state_dict)
        self._set_frame_meta(state_dict["frame_ring"]["meta"], state_dict["frame_ring"]["ring"])

    def dumps(self, path: str | Path) -> None:
        """TorchRL's storage checkpoint (per-transition part) plus the used part of the ring."""
        super().dumps(path)
        path = Path(path)
        torch.save(self._frame_meta(), path / "frame_ring_meta.pt")
        if self._ring is not None:
            np.save(path / "frame_ring.npy", self._ring[: self.frames_used].numpy())

    def loads(self, path: str | Path) -> None:
        super().loads(path)
        path = Path(path)
        ring_file = path / "frame_ring.npy"
        ring = np.load(ring_file, mmap_mode="r") if ring_file.exists() else None
        self._set_frame_meta(torch.load(path / "frame_ring_meta.pt"), ring)
