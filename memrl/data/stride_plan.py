"""Write plans of the frame ring for strided stacks (``env.frame_stride`` k > 1).

A strided stack at env step ``t`` is ``[f(t - (stack-1) k), ..., f(t - k), f(t)]``, oldest
first, with ``f(s) = f(0)`` (the reset frame) for ``s < 0``. Consecutive stacks share no frame
at k > 1, so refs cannot be shifted as at k = 1 (:func:`memrl.data.frame_plan.plan_write`):
each stream keeps the refs of its last ``span = (stack - 1) k + 1`` frames (``hist``, times
``t - span + 1 .. t``; -1 where unknown), and a transition's two stacks are read from it at
positions ``0, k, 2k, ...``. Each stored transition holds ``2 stack`` refs: ``pixels``, then
``("next", "pixels")``.

Per row of stream ``s`` (rows in write order; a write holds whole steps of ``S`` streams):

- continuation (its ``pixels`` equal the stream's previous ``("next", "pixels")``): its refs
  are those; otherwise a reset stack (one frame repeated) pushes that frame once and fills the
  whole history with it, and any other stack pushes its distinct consecutive frames (history
  unknown between them);
- the new frame (``next_pixels[-1]``) is pushed and the history shifts by one;
- next-stack frames the history does not know are pushed (never for env data); the known ones
  must equal the data (else ``ValueError``: not a strided stack).

Env data therefore pushes 1 frame per continuing row and 2 per episode start, as at k = 1; the
ring bound is in :mod:`memrl.data.frame_store`. Plans run step by step (vectorised over
streams) in torch on the ring's device; the history's frames are mirrored (``span`` frames per
stream, temporaries of one write) so checks never read frames not yet in the ring.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase

__all__ = ["StridePlan", "count_strided", "plan_strided", "span"]


def span(stack: int, stride: int) -> int:
    """Frames from a strided stack's oldest to its newest, both included."""
    return (int(stack) - 1) * int(stride) + 1


@dataclass
class StridePlan:
    """Refs of the rows of a write and the frames it pushes, in push order.

    Attributes:
        refs: ``[n, 2 stack]`` int64: ``pixels`` refs, then ``("next", "pixels")`` refs.
        pushed_refs: ``[P]`` counters of the pushed frames (``head .. head + P - 1``).
        pushed: ``[P, H, W]`` those frames.
        hist: ``[S, span]`` each stream's history of refs after the write (-1: unknown).
        hist_frames: ``[S, span, H, W]`` its frames (anything where unknown).
        bad: a row whose next stack does not match its history (-1: none).
    """

    refs: torch.Tensor
    pushed_refs: torch.Tensor
    pushed: torch.Tensor
    hist: torch.Tensor
    hist_frames: torch.Tensor
    bad: int


def plan_strided(p: torch.Tensor, q: torch.Tensor, head: int, streams: int, stride: int,
                 hist: torch.Tensor | None, hist_frames: torch.Tensor | None) -> StridePlan:
    """Plan a write of ``n`` rows (``n`` a multiple of ``streams``) of strided stacks.

    Args:
        p, q: ``pixels`` and ``("next", "pixels")``, ``[n, stack, H, W]``.
        head: frames pushed so far (the counter of the next push).
        streams: interleaved streams ``S``.
        stride: k.
        hist: ``[S, span]`` refs of each stream's last frames (-1: unknown); None: none yet.
        hist_frames: ``[S, span, H, W]`` their content (anything where unknown); updated in
            place (the plan's :attr:`StridePlan.hist_frames` is this tensor).
    """
    n, stack = p.shape[0], p.shape[1]
    sp, dev = span(stack, stride), p.device
    cols = torch.arange(0, sp, stride, device=dev)  # positions of a stack's frames
    if hist is None:
        hist = torch.full((streams, sp), -1, dtype=torch.long, device=dev)
        hist_frames = torch.zeros((streams, sp, *p.shape[2:]), dtype=p.dtype, device=dev)
    assert hist_frames is not None
    hist = hist.clone()  # the caller's stays as it was if the write is refused
    refs = torch.empty((n, 2 * stack), dtype=torch.long, device=dev)
    out_refs: list[torch.Tensor] = []
    out_frames: list[torch.Tensor] = []
    bad = -1

    def push(frames: torch.Tensor) -> torch.Tensor:
        nonlocal head
        ids = torch.arange(head, head + len(frames), device=dev)
        head += len(frames)
        out_refs.append(ids)
        out_frames.append(frames)
        return ids

    def rows(start: int, sel: torch.Tensor, cont: torch.Tensor) -> None:
        """Rows ``start + sel`` of one step, pushed in row order (``sel`` ascending)."""
        nonlocal hist, hist_frames, bad
        pi, qi = p[start + sel], q[start + sel]
        for i, s in enumerate(sel.tolist()):
            if bool(cont[i]):
                continue
            frames = pi[i]
            if bool((frames == frames[:1]).all()):  # a reset stack: f(s) = f(0) before the start
                hist[s] = push(frames[:1])[0]
                hist_frames[s] = frames[0]
            else:  # any stack: its distinct consecutive frames, the history between unknown
                new = torch.ones(stack, dtype=torch.bool, device=dev)
                new[1:] = (frames[1:] != frames[:-1]).flatten(1).any(1)
                ids = push(frames[new])
                hist[s] = -1
                hist[s, cols] = ids[torch.cumsum(new.long(), 0) - 1]
                hist_frames[s, cols] = frames
        refs[start + sel, :stack] = hist[sel[:, None], cols]
        newest = push(qi[:, -1])
        hist[sel] = torch.cat([hist[sel, 1:], newest[:, None]], 1)
        hist_frames[sel] = torch.cat([hist_frames[sel, 1:], qi[:, -1:]], 1)
        known_next = hist[sel[:, None], cols] >= 0
        same = (hist_frames[sel[:, None], cols] == qi).flatten(2).all(2)
        if bad < 0 and bool((known_next & ~same).any()):
            bad = start + int(sel[torch.nonzero((known_next & ~same).any(1))[0, 0]])
        for i, j in torch.nonzero(~known_next).tolist():  # never for env data
            s = int(sel[i])
            hist[s, cols[j]] = push(qi[i, j:j + 1])[0]
            hist_frames[s, cols[j]] = qi[i, j]
        refs[start + sel, stack:] = hist[sel[:, None], cols]

    every = torch.arange(streams, device=dev)
    for start in range(0, n, streams):
        known = (hist[:, cols] >= 0).all(1)
        cont = known & (p[start:start + streams] == hist_frames[:, cols]).flatten(1).all(1)
        if bool(cont.all()):  # one push per row: all streams at once, row order kept
            rows(start, every, cont)
        else:  # rows with more pushes: one at a time, in row order
            for s in range(streams):
                rows(start, every[s:s + 1], cont[s:s + 1])
    empty = torch.empty((0, *p.shape[2:]), dtype=p.dtype, device=dev)
    return StridePlan(refs=refs,
                      pushed_refs=torch.cat(out_refs) if out_refs else torch.empty(0, dtype=torch.long),
                      pushed=torch.cat(out_frames) if out_frames else empty,
                      hist=hist, hist_frames=hist_frames, bad=bad)


def not_strided_message(row: int, stride: int) -> str:
    """The error for a row whose next stack the env's strided stacking could not have made."""
    return (f"transition {row}: ('next', 'pixels') is not the next stack of stride {stride} "
            "(frames t-3k, t-2k, t-k, t): it cannot be stored compactly")


def count_strided(data: TensorDictBase, pixels_key: str = "pixels", streams: int = 1,
                  stride: int = 2, chunk: int = 512) -> int:
    """Frames that storing ``data`` of strided stacks (in order, into an empty store) pushes."""
    if len(data) % streams:
        raise ValueError(f"{len(data)} rows are not whole steps of {streams} streams")
    head, hist, hist_frames = 0, None, None
    step = max(streams, chunk // streams * streams)
    for start in range(0, len(data), step):
        part = data[start:start + step]
        plan = plan_strided(part.get(pixels_key), part.get(("next", pixels_key)), head, streams,
                            stride, hist, hist_frames)
        if plan.bad >= 0:
            raise ValueError(not_strided_message(start + plan.bad, stride))
        head += len(plan.pushed_refs)
        hist, hist_frames = plan.hist, plan.hist_frames
    return head

