"""The compact frame store: sampled stacks equal what the env produced, the ring-size bound,
checkpoints, and mode A / demo buffers sampling the same batches as full-stack storage."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import TensorDictReplayBuffer

from memrl.data.buffers import PriorKnowledgeBuffer, agent_buffer, demo_buffer
from memrl.data.frame_store import (
    FrameRingOverflow,
    FrameStackStorage,
    count_frames,
    ring_frames,
)
from memrl.data.transitions import to_transitions
from memrl.envs.torchrl_env import make_env
from tests.helpers import make_demos

H = W = 6  # small frames: the layout logic does not depend on the size


@pytest.fixture(scope="module")
def env_transitions():
    """Transitions of the real env pipeline with random actions: short, crashing episodes."""
    torch.manual_seed(0)
    env = make_env({"duration": 15, "vehicles_count": 3}, seed=0)
    td = env.rollout(160, break_when_any_done=False)
    out = to_transitions(td)
    assert int(out["next", "done"].sum()) >= 4  # several episode starts inside the data
    return out


def equal_td(a, b) -> bool:
    keys = ["pixels", ("next", "pixels"), "action", ("next", "reward"), ("next", "done"),
            ("next", "terminated"), "is_demo"]
    return all(torch.equal(a[k], b[k]) for k in keys)


def test_stacks_rebuilt_from_the_ring_equal_what_the_env_produced(env_transitions):
    data, capacity = env_transitions, 40  # 160 steps through 40 slots: the FIFO wraps 4 times
    rb = agent_buffer(capacity, batch_size=16)
    storage = rb.storage
    assert isinstance(storage, FrameStackStorage)
    for t in range(len(data)):  # as the training loop writes: one env step at a time
        rb.extend(data[t:t + 1])
        if t % 9 == 0 or t == len(data) - 1:  # every live transition, now and then
            live = torch.arange(max(0, t + 1 - capacity), t + 1)
            assert equal_td(storage.get(live % capacity), data[live])
    # uniform samples carry their storage index: each equals the original transition
    torch.manual_seed(1)
    for _ in range(10):
        batch = rb.sample()
        first = len(data) - capacity
        original = first + (batch["index"] - first % capacity) % capacity
        assert equal_td(batch, data[original])
    # each env frame is held once: one push per step plus one per episode start
    starts = 1 + int(data["next", "done"][:-1].sum())
    assert storage._head == len(data) + starts
    assert storage.ring_size == ring_frames(capacity) == 2 * capacity + 3


def test_a_bulk_write_stores_the_same_as_step_by_step_writes(env_transitions):
    one, bulk = agent_buffer(500, 8), agent_buffer(500, 8)
    for t in range(len(env_transitions)):
        one.extend(env_transitions[t:t + 1])
    bulk.extend(env_transitions)
    idx = torch.arange(len(env_transitions))
    assert equal_td(one.storage.get(idx), bulk.storage.get(idx))
    assert equal_td(bulk.storage.get(idx), env_transitions)


def synthetic(lengths: list[int], start: int = 1) -> TensorDict:
    """Episodes as CatFrames(padding='same') stacks them; frame k is filled with k (mod 256)."""
    rows_p, rows_q, ids = [], [], []
    frame = start
    for length in lengths:
        frames = [frame] * 4  # reset frame repeated
        frame += 1
        for _ in range(length):
            nxt = frames[1:] + [frame]
            frame += 1
            rows_p.append(frames)
            rows_q.append(nxt)
            frames = nxt
            ids.append(len(ids))
    def stack(rows):  # noqa: E306
        t = torch.tensor(rows, dtype=torch.long) % 256
        return t[..., None, None].expand(-1, -1, H, W).to(torch.uint8).contiguous()
    n = len(rows_p)
    done = torch.zeros(n, 1, dtype=torch.bool)
    return TensorDict({"pixels": stack(rows_p), "action": torch.tensor(ids),
                       "is_demo": torch.zeros(n, dtype=torch.bool),
                       "next": {"pixels": stack(rows_q), "reward": torch.zeros(n, 1),
                                "done": done, "terminated": done, "truncated": done}}, [n])


def worst_case(capacity: int) -> TensorDict:
    """A continuation of a long episode followed by one-step episodes: 2 pushes each."""
    return synthetic([8] + [1] * (3 * capacity))


def test_the_ring_bound_holds_for_the_worst_episode_lengths_and_is_tight():
    capacity = 10
    data = worst_case(capacity)
    store = FrameStackStorage(capacity)  # ring_frames(10) = 23 frames
    rb = TensorDictReplayBuffer(storage=store, batch_size=4)
    for t in range(len(data)):
        rb.extend(data[t:t + 1])
        live = torch.arange(max(0, t + 1 - capacity), t + 1)
        assert equal_td(store.get(live % capacity), data[live])
    # one frame fewer: the continuation's oldest frame would be overwritten while it is live
    small = TensorDictReplayBuffer(
        storage=FrameStackStorage(capacity, frames=ring_frames(capacity) - 1), batch_size=4)
    with pytest.raises(FrameRingOverflow):
        for t in range(len(data)):
            small.extend(data[t:t + 1])


def test_stacks_that_do_not_shift_by_one_frame_are_refused():
    data = synthetic([5])
    data["next", "pixels"][2, 0] += 1
    with pytest.raises(ValueError, match="shifted by one frame"):
        agent_buffer(10, 2).extend(data)


def test_dumps_and_loads_resume_the_ring_exactly(tmp_path, env_transitions):
    a, b = agent_buffer(30, 8), agent_buffer(30, 8)
    a.extend(env_transitions[:100])
    a.dumps(tmp_path / "rb")
    b.loads(tmp_path / "rb")
    idx = torch.arange(30)
    assert equal_td(a.storage.get(idx), b.storage.get(idx))
    for t in range(100, len(env_transitions)):  # continuations across the checkpoint
        a.extend(env_transitions[t:t + 1])
        b.extend(env_transitions[t:t + 1])
    assert equal_td(a.storage.get(idx), b.storage.get(idx))
    assert a.storage._head == b.storage._head
    c = agent_buffer(30, 8)
    c.storage.load_state_dict(a.storage.state_dict())
    assert equal_td(c.storage.get(idx), a.storage.get(idx))


def test_shuffled_demos_get_an_exact_ring_and_come_back_unchanged():
    demos = make_demos(90)
    shuffled = demos[torch.randperm(90, generator=torch.Generator().manual_seed(0))]
    rb = demo_buffer(shuffled)
    assert rb.storage.ring_size == count_frames(shuffled) <= 5 * 90
    assert count_frames(demos) < 2 * 90  # in recorded order: about one frame per transition
    assert equal_td(rb.storage.get(torch.arange(90)), shuffled)


@pytest.mark.parametrize("sampling", ["stratified", "proportional"])
def test_mode_a_samples_the_same_batches_as_full_stack_storage(env_transitions, sampling):
    demos = make_demos(60)
    bufs = [PriorKnowledgeBuffer(demos, capacity=200, demo_fraction=0.1, batch_size=16,
                                 sampling=sampling, compact=c) for c in (True, False)]
    for rb in bufs:
        rb.extend(env_transitions)  # 160 agent steps into 180 slots
    for seed in range(5):
        torch.manual_seed(seed)
        x = bufs[0].sample()
        torch.manual_seed(seed)
        y = bufs[1].sample()
        assert equal_td(x, y) and bufs[0].last_demo_count == bufs[1].last_demo_count
