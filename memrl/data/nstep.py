"""n-step returns built at sampling time from the stored 1-step transitions.

Every buffer stores 1-step transitions as today; a storage made with ``n_step = n > 1``
(:func:`nstep_storage`) returns, for each sampled transition ``t``, its n-step form:

- ``("next", "reward")``: ``sum_{i < m} gamma^i r_{t+i}`` (float64 sum in that order, cast to
  the reward's dtype);
- ``("next", ...)`` (pixels, done, terminated, truncated): those of transition ``t + m - 1``;
- ``steps_to_next_obs``: ``m``, which TorchRL's TD(0) estimator (``DQNLoss``'s) turns into the
  bootstrap discount ``gamma ** m``.

The window ``t, t+1, ..., t+m-1`` is the longest prefix, of at most ``n`` transitions, in which
each transition follows the one before in the same stream: stored right after it (``S`` rows
later for ``S`` interleaved env streams: a FIFO writer puts each write into consecutive slots,
so the next step of a stream is always ``S`` slots on, modulo the capacity), its ``pixels``
continuing the previous ``("next", "pixels")`` (same frame refs in a frame ring, same content
otherwise), and the previous one not done. So a window stops

- at a termination (crash): the sum ends with it and ``terminated`` is true: no bootstrap;
- at a time-limit truncation: ``terminated`` false, bootstrap from its last observation;
- at a gap (a demo step that was not stored, a held-out demo) or at the newest stored
  transition of the stream: bootstrap from the last observation with ``m < n`` (the same
  transition sampled later, once its successors are stored, gets the longer window).

Which rows follow which is checked with a per-row write counter (``nstep_row``) stored with the
transitions, so it survives TorchRL's ``dumps``/``loads`` and FIFO wrap-around: there is no
pending per-stream state to checkpoint, and a resumed buffer samples exactly what the
uninterrupted one would. The frame ring holds refs only (no frame is copied for a window).

``n_step = 1`` uses the plain storages (nothing added: the same samples, bit for bit).
"""

from __future__ import annotations

from typing import Any

import torch

from memrl.data.frame_store import REFS_KEY, FrameStackStorage
from memrl.data.host_draw import HostDrawStorage

__all__ = ["ROW_KEY", "STEPS_KEY", "NStepFrameStackStorage", "NStepLazyTensorStorage",
           "nstep_storage"]

ROW_KEY = "nstep_row"
"""Per-transition write counter (int64): the order transitions were written in."""
STEPS_KEY = "steps_to_next_obs"
"""Steps summed per sampled transition (TorchRL's key for the bootstrap's ``gamma ** m``)."""
_SCALARS = (("next", "reward"), ("next", "done"), ("next", "terminated"))


class _NStep:
    """Mixin over a TorchRL tensor storage: row counters on write, n-step windows on read."""

    n_step: int
    gamma: float
    streams: int
    _next_row: int | None

    def _init_nstep(self, n_step: int, gamma: float) -> None:
        if int(n_step) < 1:
            raise ValueError(f"n_step must be >= 1, got {n_step}")
        self.n_step, self.gamma, self._next_row = int(n_step), float(gamma), 0

    # ------------------------------------------------------------------ write
    def set(self, cursor: Any, data: Any, *, set_cursor: bool = True) -> None:  # type: ignore[override]
        if data.batch_dims == 0:
            data, cursor = data.unsqueeze(0), torch.as_tensor([int(cursor)])
        if ROW_KEY not in data.keys():  # the outer call (a frame ring splits large writes)
            if self._next_row is None:
                self._next_row = self._rows_written()
            data = data.clone(False)
            data.set(ROW_KEY, torch.arange(self._next_row, self._next_row + data.shape[0],
                                           device=data.device))
            self._next_row += data.shape[0]
        super().set(cursor, data, set_cursor=set_cursor)  # type: ignore[misc]

    def _rows_written(self) -> int:
        size = len(self)  # type: ignore[arg-type]
        if not size:
            return 0
        return int(self._storage.get(ROW_KEY)[:size].max()) + 1  # type: ignore[attr-defined]

    def _empty(self) -> None:
        super()._empty()  # type: ignore[misc]
        self._next_row = 0

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        super().load_state_dict(state_dict)  # type: ignore[misc]
        self._next_row = None

    def loads(self, path: Any) -> None:
        super().loads(path)  # type: ignore[misc]
        self._next_row = None

    # ------------------------------------------------------------------ read
    def _continues(self, prev: torch.Tensor, nxt: torch.Tensor) -> torch.Tensor:
        """``[B]`` bool: rows ``nxt`` start where rows ``prev`` end (same pixels)."""
        raise NotImplementedError

    def get(self, index: Any) -> Any:
        if isinstance(index, int | slice) or not isinstance(index, torch.Tensor) \
                or index.ndim != 1:
            if isinstance(index, int):
                return self.get(torch.tensor([index]))[0]
            idx = torch.arange(len(self))[index] if isinstance(index, slice) \
                else torch.as_tensor(index).reshape(-1)
            return self.get(idx)
        size, s, n = len(self), self.streams, self.n_step  # type: ignore[arg-type]
        cap = self.max_size  # type: ignore[attr-defined]
        idx = index.to(torch.long).cpu()
        rows = self._storage.get(ROW_KEY)  # type: ignore[attr-defined]
        flags = self._storage.select(*_SCALARS)  # type: ignore[attr-defined]
        dev, b = rows.device, len(idx)
        ahead = torch.arange(n, device=dev) * s
        first = idx.to(dev)
        cur = (first[:, None] + ahead) % cap  # [B, n]: the stream's next n - 1 slots
        # slot j holds step t + j of the stream: written j S rows after t (and written at all)
        ok = (cur < size) & (rows[cur] == rows[first][:, None] + ahead)
        ok[:, 0] = True
        done = flags.get(("next", "done"))[cur].reshape(b, n)
        ok[:, 1:] &= ~done[:, :-1]
        ok[:, 1:] &= self._continues(cur[:, :-1].reshape(-1), cur[:, 1:].reshape(-1)).reshape(b, -1)
        alive = ok.long().cumprod(1).bool()  # the window: the run of steps from t on
        steps = alive.sum(1)
        reward = flags.get(("next", "reward"))[first]
        rewards = flags.get(("next", "reward"))[cur].to(torch.float64)  # [B, n, 1]
        total = rewards[:, 0]
        for j in range(1, n):  # left to right, as by hand
            total = torch.where(alive[:, j, None], total + self.gamma ** j * rewards[:, j], total)
        last = cur[torch.arange(b, device=dev), steps - 1]
        out = super().get(idx)  # type: ignore[misc]
        if bool((last != first).any()):
            out.set("next", super().get(last.cpu()).get("next"))  # type: ignore[misc]
        out.set(("next", "reward"), total.to(reward.dtype).to(out.device))
        out.set(STEPS_KEY, steps.reshape(-1, 1).to(out.device))
        return out.exclude(ROW_KEY)


class NStepFrameStackStorage(_NStep, FrameStackStorage):
    """:class:`FrameStackStorage` sampling n-step transitions (see the module docstring).

    Args:
        max_size: transitions held.
        n_step: steps summed at most (>= 1).
        gamma: discount of the sum.
        **kwargs: :class:`FrameStackStorage`'s.
    """

    def __init__(self, max_size: int, *, n_step: int, gamma: float, **kwargs: Any) -> None:
        super().__init__(max_size, **kwargs)
        self._init_nstep(n_step, gamma)

    def _continues(self, prev: torch.Tensor, nxt: torch.Tensor) -> torch.Tensor:
        refs = self._storage.get(REFS_KEY)
        return (refs[nxt][:, : self.stack] == refs[prev][:, -self.stack:]).all(1)


class NStepLazyTensorStorage(_NStep, HostDrawStorage):
    """TorchRL ``LazyTensorStorage`` (full stacks) sampling n-step transitions.

    Args:
        max_size: transitions held.
        n_step: steps summed at most (>= 1).
        gamma: discount of the sum.
        streams: interleaved env streams (row ``r`` of a write is stream ``r % streams``).
        device: where the transitions live.
        pixels_key: the stacked key compared for continuation.
    """

    def __init__(self, max_size: int, *, n_step: int, gamma: float, streams: int = 1,
                 device: torch.device | str = "cpu", pixels_key: str = "pixels") -> None:
        super().__init__(max_size, device=device)
        self.streams, self.pixels_key = int(streams), pixels_key
        self._init_nstep(n_step, gamma)

    def _continues(self, prev: torch.Tensor, nxt: torch.Tensor) -> torch.Tensor:
        p = self._storage.get(self.pixels_key)[nxt]
        q = self._storage.get(("next", self.pixels_key))[prev]
        return (p == q).reshape(len(p), -1).all(1)


def nstep_storage(max_size: int, *, compact: bool, n_step: int = 1, gamma: float = 0.99,
                  streams: int = 1, device: torch.device | str = "cpu",
                  frames: int | None = None, stride: int = 1) -> Any:
    """A storage of ``max_size`` 1-step transitions, sampled as ``n_step`` ones.

    ``n_step = 1``: TorchRL's ``LazyTensorStorage`` or :class:`FrameStackStorage`, unchanged.

    Args:
        max_size: transitions held.
        compact: a frame ring (each frame once) instead of full stacks.
        n_step: steps summed at most.
        gamma: discount of the sum.
        streams: interleaved env streams.
        device: where transitions live and samples come back.
        frames: ring size (compact only; default: the bound for env data).
        stride: frames between the stacked frames (compact only; ``env.frame_stride``).
    """
    ring: dict[str, Any] = {"streams": streams, "device": device, "frames": frames}
    if stride != 1:
        ring["stride"] = stride
    if n_step == 1:
        return (FrameStackStorage(max_size, **ring) if compact
                else HostDrawStorage(max_size, device=device))
    if compact:
        return NStepFrameStackStorage(max_size, n_step=n_step, gamma=gamma, **ring)
    return NStepLazyTensorStorage(max_size, n_step=n_step, gamma=gamma, streams=streams,
                                  device=device)
