"""Strided stacks in the replay frame ring (env.frame_stride k): stacks rebuilt from per-stream
histories of refs, the ring bound (tight), checkpoints, n-step on top."""

from __future__ import annotations

import pytest
import torch
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from memrl.data.buffers import agent_buffer, demo_buffer
from memrl.data.frame_store import FrameRingOverflow, FrameStackStorage, ring_frames
from memrl.data.nstep import STEPS_KEY
from tests.nstep_ref import reference
from tests.stream_data import STACK, stream_steps

K = 3
SPAN = (STACK - 1) * K + 1  # frames a strided stack spans: t-9 .. t


def same(a, b) -> bool:
    a, b = a.exclude("index"), b.exclude("index")  # TensorDictReplayBuffer stores its own
    return set(a.keys(True, True)) == set(b.keys(True, True)) and bool((a == b).all())


def test_synthetic_strided_stacks_are_what_the_env_emits():
    steps = stream_steps(1, 12, lengths=[[12]], stride=K)
    # frame id k is pixel (0, 0); time s has id s + 1 (the reset frame, id 1, at s <= 0).
    # Step t's next stack: times t+1-9, t+1-6, t+1-3, t+1
    nxt = [steps[t]["next", "pixels"][0, :, 0, 0].tolist() for t in (0, 3, 11)]
    assert nxt == [[1, 1, 1, 2], [1, 1, 2, 5], [4, 7, 10, 13]]


@pytest.mark.parametrize("streams", [1, 3])
@pytest.mark.parametrize("numpy", [True, False])
def test_rows_read_back_equal_the_written_strided_data(streams, numpy):
    data = stream_steps(streams, 40, seed=streams, max_len=14, stride=K)
    store = FrameStackStorage(400, streams=streams, stride=K, numpy=numpy)
    rb = TensorDictReplayBuffer(storage=store, batch_size=4)
    for step in data:
        rb.extend(step)
    rows = torch.cat(data)
    assert same(store.get(torch.arange(len(rows))), rows)
    # each frame pushed once: one per row, one more per episode start (reset stack)
    starts = int((rows["pixels"] == rows["pixels"][:, :1]).flatten(1).all(1).sum())
    assert store._head == len(rows) + starts
    assert store.ring_size == ring_frames(400, STACK, streams, K) == 2 * 400 - 1 + (2 * streams - 1) * SPAN


def test_a_write_of_many_steps_plans_like_one_step_writes():
    data = stream_steps(2, 30, seed=3, max_len=12, stride=K)
    one, many = FrameStackStorage(60, streams=2, stride=K), FrameStackStorage(60, streams=2, stride=K)
    a, b = (TensorDictReplayBuffer(storage=s, batch_size=4) for s in (one, many))
    for step in data:
        a.extend(step)
    b.extend(torch.cat(data))
    idx = torch.arange(60)
    assert same(one.get(idx), many.get(idx)) and one._head == many._head


def worst_case(streams: int, capacity: int):
    """Env 0 continues for ``SPAN + 1`` steps, every other row is a one-step episode."""
    lengths = [[SPAN + 1]] + [[] for _ in range(streams - 1)]
    return stream_steps(streams, SPAN + capacity // streams + 3, max_len=1, lengths=lengths,
                        stride=K)


@pytest.mark.parametrize("streams", [1, 3])
def test_the_strided_ring_bound_holds_at_its_worst_case_and_is_tight(streams):
    capacity = 4 * streams
    data = worst_case(streams, capacity)
    bound = ring_frames(capacity, STACK, streams, K)
    plain = TensorDictReplayBuffer(storage=LazyTensorStorage(capacity), batch_size=2)
    ring = TensorDictReplayBuffer(storage=FrameStackStorage(capacity, streams=streams, stride=K),
                                  batch_size=2)
    for step in data:
        plain.extend(step)
        ring.extend(step)
        n = len(plain)
        assert same(ring.storage.get(torch.arange(n)), plain.storage.get(torch.arange(n)))
    small = TensorDictReplayBuffer(
        storage=FrameStackStorage(capacity, streams=streams, stride=K, frames=bound - 1),
        batch_size=2)
    with pytest.raises(FrameRingOverflow):
        for step in data:
            small.extend(step)


def test_stacks_that_are_not_strided_are_refused():
    data = torch.cat(stream_steps(1, 6, lengths=[[6]]))  # stride 1 data
    rb = TensorDictReplayBuffer(storage=FrameStackStorage(10, stride=K), batch_size=2)
    with pytest.raises(ValueError, match="not the next stack of stride 3"):
        rb.extend(data)


@pytest.mark.parametrize("n", [1, 3])
def test_checkpoint_mid_episode_resumes_exactly(tmp_path, n):
    data = stream_steps(2, 50, seed=9, max_len=15, stride=K)
    a = agent_buffer(30, 4, streams=2, n_step=n, gamma=0.9, stride=K)
    for step in data[:23]:
        a.extend(step)
    a.dumps(tmp_path / "rb")
    b = agent_buffer(30, 4, streams=2, n_step=n, gamma=0.9, stride=K)
    b.loads(tmp_path / "rb")
    for step in data[23:]:
        a.extend(step)
        b.extend(step)
    idx = torch.arange(30)
    assert same(a.storage.get(idx), b.storage.get(idx))
    assert a.storage._head == b.storage._head


@pytest.mark.parametrize("n", [3, 10])
def test_n_step_windows_over_strided_stacks_match_the_reference(n):
    steps = stream_steps(3, 30, seed=n, max_len=12, stride=K)
    rb = agent_buffer(300, 8, streams=3, n_step=n, gamma=0.9, stride=K)
    for td in steps:
        rb.extend(td)
    got, want = rb.storage.get(torch.arange(len(rb))), reference(steps, n, 0.9)
    for i, w in enumerate(want):
        assert torch.equal(got["next", "reward"][i], w["reward"]), i
        assert int(got[STEPS_KEY][i]) == w["m"]
        assert torch.equal(got["next", "pixels"][i], w["next_pixels"]), i


def test_strided_demos_fill_a_ring_of_exactly_their_frames():
    rows = torch.cat(stream_steps(1, 40, seed=2, max_len=15, stride=K))
    keep = torch.ones(len(rows), dtype=torch.bool)
    keep[[5, 17]] = False  # unstored steps: the next row starts a fresh history
    demos = rows[keep]
    rb = demo_buffer(demos, compact=True, stride=K)
    assert same(rb.storage.get(torch.arange(len(demos))), demos)


def test_a_strided_dataset_saves_each_frame_once_and_loads_back(tmp_path):
    from memrl.data.demos import load_demos, read_metadata, save_demos

    rows = torch.cat(stream_steps(1, 30, seed=5, max_len=12, size=84, stride=K))
    rows["action"] = rows["action"] % 9  # in the action range, flagged as demos
    rows["is_demo"][:] = True
    path = save_demos([rows[:13], rows[13:]], tmp_path / "d", {"env_config": {}, "frame_stride": K})
    meta = read_metadata(path)
    starts = int((rows["pixels"] == rows["pixels"][:, :1]).flatten(1).all(1).sum())
    assert meta["frame_stride"] == K and meta["counts"]["frames"] == len(rows) + starts
    assert same(load_demos(path), rows)
    # the same data recorded at k = 1 is refused (its next stacks are not shifted stacks)
    with pytest.raises(ValueError, match="shifted by one frame"):
        save_demos(rows, tmp_path / "e", {"env_config": {}})


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_strided_n_step_buffer_on_cuda_equals_the_cpu_one():
    data = stream_steps(4, 40, seed=11, max_len=12, stride=K)
    cpu = agent_buffer(100, 8, streams=4, n_step=3, gamma=0.9, stride=K)
    gpu = agent_buffer(100, 8, streams=4, n_step=3, gamma=0.9, stride=K, device="cuda")
    for step in data:
        cpu.extend(step)
        gpu.extend(step)
    idx = torch.arange(100)
    assert same(cpu.storage.get(idx), gpu.storage.get(idx).cpu())
