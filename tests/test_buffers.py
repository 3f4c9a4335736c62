"""Replay buffers of the modes: exact stratification, protected demos, FIFO agent data."""

from __future__ import annotations

import torch
from tensordict import TensorDict

from memrl.data.buffers import PriorKnowledgeBuffer, agent_buffer


def fake(n: int, demo: bool, start: int = 0) -> TensorDict:
    """Transitions whose action field numbers them, so we can tell which survived."""
    z = lambda *s: torch.zeros(n, *s, dtype=torch.uint8)  # noqa: E731
    f = lambda: torch.zeros(n, 1, dtype=torch.bool)  # noqa: E731
    return TensorDict({"pixels": z(4, 84, 84), "action": torch.arange(start, start + n),
                       "is_demo": torch.full((n,), demo),
                       "next": {"pixels": z(4, 84, 84), "reward": torch.zeros(n, 1),
                                "done": f(), "terminated": f(), "truncated": f()}}, [n])


def test_stratified_batches_hold_exactly_the_configured_demo_count():
    torch.manual_seed(0)
    rb = PriorKnowledgeBuffer(fake(500, True), capacity=1000, demo_fraction=0.1, batch_size=32)
    rb.extend(fake(50, False, start=10_000))
    counts = {int(rb.sample()["is_demo"].sum()) for _ in range(200)}
    assert counts == {round(0.1 * 32)} and rb.last_demo_count == 3
    counts = {int(rb.sample(100)["is_demo"].sum()) for _ in range(50)}
    assert counts == {10}


def test_demos_keep_their_slice_and_agent_data_is_fifo():
    rb = PriorKnowledgeBuffer(fake(500, True), capacity=1000, demo_fraction=0.1, batch_size=32)
    assert len(rb.offline_buffer) == 100  # 10% of the capacity; extra demos are left out
    for k in range(30):  # 3000 agent transitions through a 900-slot FIFO
        rb.extend(fake(100, False, start=10_000 + 100 * k))
    assert len(rb) == 1000 and len(rb.online_buffer) == 900
    demos = rb.offline_buffer.storage.get(torch.arange(100))
    assert demos["is_demo"].all() and torch.equal(demos["action"], torch.arange(100))
    agent = rb.online_buffer.storage.get(torch.arange(900))
    assert sorted(agent["action"].tolist()) == list(range(10_000 + 2100, 10_000 + 3000))


def test_proportional_sampling_matches_the_demo_share_on_average():
    torch.manual_seed(0)
    rb = PriorKnowledgeBuffer(fake(100, True), capacity=1000, demo_fraction=0.1, batch_size=32,
                              sampling="proportional")
    rb.extend(fake(300, False, start=10_000))  # demos are 100 of 400 stored: share 0.25
    counts = torch.tensor([float(rb.sample()["is_demo"].sum()) for _ in range(400)])
    assert abs(counts.mean().item() - 0.25 * 32) < 0.5
    assert counts.min() < counts.max()  # not stratified


def test_default_buffer_is_fifo_with_uniform_sampling():
    rb = agent_buffer(capacity=100, batch_size=10)
    rb.extend(fake(250, False))
    kept = rb.storage.get(torch.arange(100))["action"]
    assert sorted(kept.tolist()) == list(range(150, 250))
    assert len(rb.sample()) == 10
