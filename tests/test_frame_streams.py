"""The frame store with S interleaved env streams: exactly what full-stack storage gives, the
ring bound for S streams at its worst case, checkpoints mid-stream, and mode A."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tensordict import TensorDictBase
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from memrl.data.buffers import PriorKnowledgeBuffer
from memrl.data.frame_store import FrameRingOverflow, FrameStackStorage, ring_frames
from tests.stream_data import STACK, stream_steps

BACKENDS = pytest.mark.parametrize("numpy", [True, False], ids=["numpy", "torch"])


def same(a: TensorDictBase, b: TensorDictBase) -> bool:
    """Same keys, same values (and the stacks do not share memory)."""
    keys = set(a.keys(True, True))
    if keys != set(b.keys(True, True)):
        return False
    return all(torch.equal(a[k], b[k]) for k in keys)


def pair(capacity: int, streams: int, numpy: bool, frames: int | None = None):
    """A compact and a plain buffer of the same capacity."""
    compact = FrameStackStorage(capacity, streams=streams, numpy=numpy, frames=frames)
    return [TensorDictReplayBuffer(storage=s, batch_size=16)
            for s in (compact, LazyTensorStorage(capacity))]


def all_rows_equal(rbs) -> bool:
    idx = torch.arange(len(rbs[1]))
    return len(rbs[0]) == len(rbs[1]) and same(rbs[0].storage.get(idx), rbs[1].storage.get(idx))


@BACKENDS
@pytest.mark.parametrize(("streams", "capacity", "steps"), [(3, 50, 150), (16, 72, 40)])
def test_streams_store_exactly_what_full_stacks_store(streams, capacity, steps, numpy):
    data = stream_steps(streams, steps, seed=streams)  # episodes of 1-12 steps, random resets
    rbs = pair(capacity, streams, numpy)
    rng, t = np.random.default_rng(0), 0
    while t < steps:  # mostly one env step per write, as the trainer; some bulk writes
        k = int(rng.choice([1, 1, 1, 2, 3]))
        part = torch.cat(data[t:t + k])  # step-major: row r is env r % streams
        for rb in rbs:
            rb.extend(part)
        t += k
        assert all_rows_equal(rbs)  # every index, after every write
    for seed in range(5):
        batches = []
        for rb in rbs:
            torch.manual_seed(seed)
            batches.append(rb.sample())
        assert same(*batches)
    # each frame pushed once: one push per row, one more per episode start (reset stack)
    rows = torch.cat(data)
    starts = int((rows["pixels"] == rows["pixels"][:, :1]).flatten(1).all(1).sum())
    store = rbs[0].storage
    assert store._head == len(rows) + starts
    assert store.ring_size == ring_frames(capacity, STACK, streams)


def worst_case(streams: int, capacity: int):
    """Env 0 continues for ``stack + 1`` steps, every other row is a one-step episode."""
    lengths = [[STACK + 1]] + [[] for _ in range(streams - 1)]
    steps = STACK + capacity // streams + 3
    return stream_steps(streams, steps, max_len=1, lengths=lengths)


@pytest.mark.parametrize("streams", [1, 3, 16])
def test_the_ring_bound_for_streams_holds_at_its_worst_case_and_is_tight(streams):
    capacity = 4 * streams
    data = worst_case(streams, capacity)
    bound = ring_frames(capacity, STACK, streams)
    assert bound == 2 * capacity - 1 + (2 * streams - 1) * STACK
    rbs = pair(capacity, streams, numpy=True)  # the bound itself: always exact
    for step in data:
        for rb in rbs:
            rb.extend(step)
        assert all_rows_equal(rbs)
    # one frame fewer: env 0's continuation loses its oldest frame while it is live
    small = pair(capacity, streams, numpy=True, frames=bound - 1)
    with pytest.raises(FrameRingOverflow):
        for step in data:
            store = small[0].storage
            before = (store._head, len(store), store.get(torch.arange(len(store)))
                      if len(store) else None)
            try:
                small[0].extend(step)
            except FrameRingOverflow:  # refused before anything changed
                assert (store._head, len(store)) == before[:2]
                assert same(store.get(torch.arange(len(store))), before[2])
                assert same(store.get(torch.arange(len(store))),
                            small[1].storage.get(torch.arange(len(store))))
                raise
            small[1].extend(step)


def test_writes_must_hold_whole_steps():
    store = FrameStackStorage(12, streams=3)
    data = torch.cat(stream_steps(3, 2))
    with pytest.raises(ValueError, match="whole steps of 3 streams"):
        TensorDictReplayBuffer(storage=store, batch_size=2).extend(data[:4])
    with pytest.raises(ValueError, match="streams must be"):
        FrameStackStorage(2, streams=3)


@BACKENDS
def test_dumps_and_loads_resume_streams_exactly(tmp_path, numpy):
    streams, capacity = 3, 40
    data = stream_steps(streams, 60, seed=5)
    a = pair(capacity, streams, numpy)
    for step in data[:30]:
        for rb in a:
            rb.extend(step)
    a[0].dumps(tmp_path / "rb")
    b = pair(capacity, streams, numpy)[0]
    b.loads(tmp_path / "rb")
    c = pair(capacity, streams, numpy)[0]
    c.load_state_dict(a[0].state_dict())  # storage, writer cursor and sampler
    for step in data[30:]:  # continuations across the checkpoint
        for rb in (*a, b, c):
            rb.extend(step)
    idx = torch.arange(capacity)
    for rb in (b, c):
        assert same(rb.storage.get(idx), a[1].storage.get(idx))
        assert rb.storage._head == a[0].storage._head
    with pytest.raises(ValueError, match="stream"):
        FrameStackStorage(capacity, frames=a[0].storage.ring_size).loads(tmp_path / "rb" / "storage")


@pytest.mark.parametrize("sampling", ["stratified", "proportional"])
def test_mode_a_with_streams_samples_what_full_stacks_give(sampling):
    demos = torch.cat(stream_steps(1, 40, seed=9))
    demos["is_demo"] = torch.ones(len(demos), dtype=torch.bool)
    bufs = [PriorKnowledgeBuffer(demos, capacity=120, demo_fraction=0.1, batch_size=16,
                                 sampling=sampling, compact=c, streams=4) for c in (True, False)]
    for step in stream_steps(4, 60, seed=4):  # 240 agent rows through 108 slots, per env step
        for rb in bufs:
            rb.extend(step)
    assert isinstance(bufs[0].online_buffer.storage, FrameStackStorage)
    for seed in range(5):
        torch.manual_seed(seed)
        x = bufs[0].sample()
        torch.manual_seed(seed)
        y = bufs[1].sample()
        assert same(x, y) and bufs[0].last_demo_count == bufs[1].last_demo_count
