"""Replay buffers of the three modes, built on TorchRL.

- Default and mode B stage 2: a ``TensorDictReplayBuffer`` over a ``LazyTensorStorage``
  (FIFO once full), uniform sampling.
- Mode A: :class:`PriorKnowledgeBuffer`, TorchRL's ``OfflineToOnlineReplayBuffer`` whose
  offline part holds the prior knowledge (``demo_fraction`` of the capacity, never
  overwritten) and whose online part holds the agent's transitions FIFO. ``stratified``
  sampling draws exactly ``round(demo_fraction * batch)`` demos per batch (TorchRL's own);
  ``proportional`` draws the demo count from a binomial with the demos' share of the stored
  transitions, which is exactly uniform sampling over one storage holding both.
- Mode B stage 1: a buffer holding only prior knowledge.

With ``compact=True`` (the default) every buffer stores each 84x84 frame once
(:class:`memrl.data.frame_store.FrameStackStorage`: a frame ring plus per-transition frame
refs; stacks are rebuilt when sampled); ``compact=False`` stores both full stacks per
transition (TorchRL's plain ``LazyTensorStorage``). Samples are the same either way.

``streams=N``: the agent's transitions arrive from N envs stepped together, one
``extend`` of N rows per env step (row i = env i; see :mod:`memrl.data.frame_store`).
``device``: where both parts store and sample; indices are drawn on the CPU on any device
(:mod:`memrl.data.host_draw`), and the batches come back on ``device``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.data import ReplayBuffer, TensorDictReplayBuffer
from torchrl.data.replay_buffers.offline_to_online import OfflineToOnlineReplayBuffer
from torchrl.data.replay_buffers.storages import Storage

from memrl.data.crash_sampler import CrashShareSampler
from memrl.data.frame_store import count_frames
from memrl.data.nstep import nstep_storage
from memrl.data.priority_sampler import INDEX_KEY, WEIGHT_KEY, PrioritySampler

NStep = dict[str, Any]
"""``n_step`` (steps summed at most, 1: 1-step), ``gamma`` and ``stride`` (frames between the
stacked frames) of a buffer's storage; see :mod:`memrl.data.nstep`."""


def agent_storage(capacity: int, compact: bool = True, streams: int = 1,
                  device: torch.device | str = "cpu", **nstep: Any) -> Storage:
    """Storage of ``capacity`` agent transitions: a frame ring (each frame once) or full stacks.

    Args:
        capacity: transitions held.
        compact: the frame ring (:class:`FrameStackStorage`), else full stacks.
        streams: envs writing interleaved rows (row ``r`` of a write is env ``r % streams``).
        device: where the transitions are stored and sampled.
        **nstep: ``n_step``, ``gamma``, ``stride`` (:data:`NStep`).
    """
    return nstep_storage(capacity, compact=compact, streams=streams, device=device, **nstep)


def agent_sampler(capacity: int, crash_share: float = 0.0, priority: float = 0.0,
                  priority_beta: float = 0.5) -> Any:
    """The agent part's sampler: prioritized (``priority`` = alpha > 0,
    :class:`~memrl.data.priority_sampler.PrioritySampler`), a crash share
    (:class:`~memrl.data.crash_sampler.CrashShareSampler`), or None: TorchRL's uniform one."""
    if priority > 0 and crash_share > 0:
        raise ValueError("buffer.priority and buffer.crash_share exclude each other")
    if priority > 0:
        return PrioritySampler(capacity, priority, priority_beta)
    return CrashShareSampler(crash_share) if crash_share > 0 else None


def agent_buffer(capacity: int, batch_size: int, compact: bool = True, streams: int = 1,
                 device: torch.device | str = "cpu", crash_share: float = 0.0,
                 priority: float = 0.0, priority_beta: float = 0.5,
                 **nstep: Any) -> TensorDictReplayBuffer:
    """FIFO replay of the agent's own transitions (see :func:`agent_storage`), sampled as
    :func:`agent_sampler` says (uniform by default). Batches carry each item's row
    (``index``) and, when prioritized, its importance weight (``priority_weight``)."""
    return TensorDictReplayBuffer(
        storage=agent_storage(capacity, compact, streams, device, **nstep), batch_size=batch_size,
        sampler=agent_sampler(capacity, crash_share, priority, priority_beta))


def priority_sampler(buffer: Any) -> PrioritySampler | None:
    """The prioritized sampler of a buffer's agent part, None when it samples otherwise."""
    rb = buffer.online_buffer if isinstance(buffer, PriorKnowledgeBuffer) else buffer
    return rb.sampler if isinstance(rb.sampler, PrioritySampler) else None


def demo_buffer(demos: TensorDictBase, batch_size: int | None = None,
                compact: bool = True, device: torch.device | str = "cpu",
                **nstep: Any) -> ReplayBuffer:
    """A buffer filled with ``demos`` (its capacity is their count: nothing else gets in).

    Demos arrive as full stacks (:func:`memrl.data.demos.load_demos` rebuilds them from either
    dataset format); a compact buffer converts them on entry, with a ring of exactly the frames
    they need (they are written once). With ``n_step > 1`` consecutive demos of an episode are
    sampled as n-step windows (:mod:`memrl.data.nstep`).
    """
    stride = int(nstep.get("stride", 1))
    frames = count_frames(demos, stride=stride) if compact else None
    storage: Storage = nstep_storage(len(demos), compact=compact, device=device, frames=frames,
                                     **nstep)
    rb = ReplayBuffer(storage=storage, batch_size=batch_size)
    rb.extend(demos)
    return rb


class PriorKnowledgeBuffer(OfflineToOnlineReplayBuffer):
    """Mode A: prior knowledge in a fixed slice of the buffer, agent data FIFO in the rest.

    Args:
        demos: prior-knowledge transitions; the first ``round(demo_fraction * capacity)`` are
            kept (all of them when there are fewer).
        capacity: total transitions (demos + agent).
        demo_fraction: share of the capacity reserved for demos.
        batch_size: default batch size.
        sampling: ``stratified`` or ``proportional``.
        compact: store each frame once (both parts), see :mod:`memrl.data.frame_store`.
        streams: envs writing the agent part together (one ``extend`` of ``streams`` rows per
            env step).
        device: where both parts store and sample.
        crash_share: share of the agent part of each batch drawn from its crash transitions
            (:class:`~memrl.data.crash_sampler.CrashShareSampler`; 0: uniform).
        priority, priority_beta: prioritized sampling of the agent part (alpha > 0; see
            :func:`agent_sampler`); demo items keep the stratified share.
        **nstep: ``n_step``, ``gamma``, ``stride`` of both parts (:data:`NStep`).
    """

    def __init__(self, demos: TensorDictBase, capacity: int, demo_fraction: float,
                 batch_size: int, sampling: str = "stratified", compact: bool = True,
                 streams: int = 1, device: torch.device | str = "cpu", crash_share: float = 0.0,
                 priority: float = 0.0, priority_beta: float = 0.5, **nstep: Any) -> None:
        if sampling not in ("stratified", "proportional"):
            raise ValueError(f"sampling must be stratified or proportional, got {sampling!r}")
        n_demo = int(round(demo_fraction * capacity))
        if len(demos) == 0:
            raise ValueError("mode A needs at least one prior-knowledge transition")
        kept = demos[: min(n_demo, len(demos))]
        super().__init__(demo_buffer(kept, compact=compact, device=device, **nstep),
                         online_storage=agent_storage(capacity - n_demo, compact, streams, device,
                                                      **nstep),
                         offline_fraction=demo_fraction, batch_size=batch_size)
        sampler = agent_sampler(capacity - n_demo, crash_share, priority, priority_beta)
        if sampler is not None:  # TorchRL builds the online part with a uniform sampler, no argument
            self._online_buffer = ReplayBuffer(storage=self._online_buffer.storage, sampler=sampler)
        self.prioritized = isinstance(sampler, PrioritySampler)
        self.sampling = sampling
        self.capacity = capacity
        self.last_demo_count = 0

    def sample(self, batch_size: int | None = None) -> TensorDictBase:
        """A batch; ``last_demo_count`` tells how many of its items are demos."""
        batch_size = batch_size or self._batch_size
        out: TensorDictBase
        if self.prioritized and len(self.online_buffer) > 0:
            out = self._sample_prioritized(batch_size)
        elif self.sampling == "proportional" and len(self.online_buffer) > 0:
            share = len(self.offline_buffer) / len(self)
            n_demo = int(torch.binomial(torch.tensor(float(batch_size)), torch.tensor(share)))
            parts = [b.sample(n) for b, n in ((self.offline_buffer, n_demo),
                                              (self.online_buffer, batch_size - n_demo)) if n > 0]
            out = torch.cat(parts) if len(parts) > 1 else parts[0]  # type: ignore[assignment]
        else:
            out = super().sample(batch_size)
        self.last_demo_count = int(out["is_demo"].sum())
        return out

    def _sample_prioritized(self, batch_size: int) -> TensorDictBase:
        """Stratified demos (first) and prioritized agent items, with each item's agent row
        (``index``: -1 for demos) and importance weight; the demos weigh the agent items'
        mean, so their share of the TD loss stays their share of the batch."""
        n_demo = int(round(self.offline_fraction * batch_size))
        agent, info = self.online_buffer.sample(batch_size - n_demo, return_info=True)
        weight, index = info[WEIGHT_KEY], torch.as_tensor(info[INDEX_KEY]).reshape(-1)
        if n_demo > 0:
            agent = torch.cat([self.offline_buffer.sample(n_demo), agent])  # type: ignore[assignment]
            weight = torch.cat([weight.mean().expand(n_demo), weight])
            index = torch.cat([torch.full((n_demo,), -1, dtype=index.dtype), index])
        agent.set(WEIGHT_KEY, weight.to(agent.device))
        agent.set(INDEX_KEY, index.to(agent.device))
        return agent

    def dumps(self, path: str | Path) -> None:
        """Save the agent part (TorchRL buffer checkpointing); the demo part is immutable and is
        rebuilt from its dataset, whose identity the checkpoint records."""
        Path(path).mkdir(parents=True, exist_ok=True)
        self.online_buffer.dumps(path)

    def loads(self, path: str | Path) -> None:
        self.online_buffer.loads(path)

