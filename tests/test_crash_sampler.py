"""buffer.crash_share: an exact share of every batch from the crash transitions, uniform
otherwise, the same samples after a kill and resume."""

from __future__ import annotations

import pytest
import torch

from memrl.data.buffers import PriorKnowledgeBuffer, agent_buffer
from memrl.data.crash_sampler import CrashShareSampler, crash_rows
from memrl.dqn.config import check_train_config
from memrl.errors import ConfigError
from tests.helpers import (
    EVERY_STAGE,
    assert_kill_and_resume_is_exact,
    built_stage_buffer,
    csv_rows,
    tiny_mode,
)
from tests.test_buffers import fake

CRASHES = [7, 42, 93]


def with_crashes(n: int, rows: list[int], start: int = 0, demo: bool = False):
    data = fake(n, demo, start=start)
    data["next", "terminated"][rows] = True
    data["next", "done"][rows] = True
    return data


@pytest.mark.parametrize("compact", [True, False])
def test_each_batch_starts_with_the_share_of_crash_rows(compact):
    torch.manual_seed(0)
    rb = agent_buffer(capacity=200, batch_size=32, compact=compact, crash_share=0.25)
    rb.extend(with_crashes(120, CRASHES))
    assert crash_rows(rb.storage).tolist() == CRASHES
    for _ in range(50):
        actions = rb.sample()["action"]
        assert len(actions) == 32
        assert set(actions[:8].tolist()) <= set(CRASHES)  # round(0.25 * 32) = 8 drawn from crashes
        assert (actions[8:] < 120).all()


def test_all_three_crash_rows_are_drawn_uniformly():
    torch.manual_seed(1)
    rb = agent_buffer(capacity=200, batch_size=32, crash_share=0.5)
    rb.extend(with_crashes(120, CRASHES))
    first = torch.cat([rb.sample()["action"][:16] for _ in range(300)])
    counts = torch.bincount(first, minlength=120)[CRASHES].float()
    # 4,800 draws over 3 rows: each count ~ Binomial(4800, 1/3), sd 32.7; 6 sd allowed
    assert counts.sum() == 4800 and ((counts - 1600).abs() < 200).all()


def test_without_crashes_or_share_it_samples_as_the_uniform_buffer():
    plain = agent_buffer(capacity=200, batch_size=32)
    shared = agent_buffer(capacity=200, batch_size=32, crash_share=0.25)
    for rb in (plain, shared):
        rb.extend(fake(120, False))
    torch.manual_seed(3)
    a = [plain.sample()["action"] for _ in range(5)]
    torch.manual_seed(3)
    b = [shared.sample()["action"] for _ in range(5)]
    assert all(torch.equal(x, y) for x, y in zip(a, b, strict=True))
    assert type(plain.sampler).__name__ == "RandomSampler"


def test_crash_rows_follow_the_fifo_overwrite():
    rb = agent_buffer(capacity=100, batch_size=8, crash_share=0.25)
    rb.extend(with_crashes(100, [5, 50]))
    rb.extend(with_crashes(10, [3], start=1000))  # overwrites rows 0-9: row 5's crash is gone
    assert crash_rows(rb.storage).tolist() == [3, 50]


def test_mode_a_keeps_its_demo_count_and_shares_the_agent_part():
    torch.manual_seed(0)
    rb = PriorKnowledgeBuffer(fake(100, True), capacity=1000, demo_fraction=0.1, batch_size=32,
                              crash_share=0.25)
    rb.extend(with_crashes(300, CRASHES, start=10_000))
    crash_actions = {10_000 + r for r in CRASHES}
    for _ in range(100):
        batch = rb.sample()
        assert int(batch["is_demo"].sum()) == 3 and rb.last_demo_count == 3
        agent = batch["action"][~batch["is_demo"]].tolist()
        assert len(agent) == 29 and set(agent[:7]) <= crash_actions  # round(0.25 * 29) = 7


def test_share_out_of_range_is_refused(compose_cfg):
    with pytest.raises(ValueError, match="crash share"):
        CrashShareSampler(1.0)
    with pytest.raises(ConfigError, match=r"config 'buffer.crash_share': must be in \[0, 1\), got 1.5"):
        check_train_config(compose_cfg("train", ["buffer.crash_share=1.5"]))


@pytest.mark.parametrize("mode", [None, "A"])
def test_run_with_a_crash_share_killed_and_resumed_equals_an_uninterrupted_one(
        compose_cfg, tmp_path, demos, monkeypatch, mode):
    extra = ["env.num_envs=4", "total_episodes=12", "checkpoint_every=3", "buffer.crash_share=0.25",
             *tiny_mode(mode)]
    assert_kill_and_resume_is_exact(compose_cfg, tmp_path, demos, monkeypatch, extra)
    assert any(row["collided"] == "1" for row in csv_rows(tmp_path / "full" / "episodes.csv"))


@pytest.mark.parametrize("mode, stage, overrides", EVERY_STAGE)
def test_every_agent_stage_samples_through_the_crash_sampler(compose_cfg, demos, mode, stage, overrides):
    rb = built_stage_buffer(compose_cfg, demos, mode, stage, ["buffer.crash_share=0.25", *overrides])
    agent_part = getattr(rb, "online_buffer", rb)
    if stage == "B1":  # prior knowledge alone: nothing crashes there, nothing to oversample
        assert not isinstance(agent_part.sampler, CrashShareSampler)
    else:
        assert isinstance(agent_part.sampler, CrashShareSampler) and agent_part.sampler.share == 0.25
