"""buffer.priority: proportional prioritized replay (draws, weights and priorities against a
hand computation, the weighted TD loss, every agent stage, and exact kill-and-resume)."""

from __future__ import annotations

import pytest
import torch

from memrl.data.buffers import PriorKnowledgeBuffer, agent_buffer, priority_sampler
from memrl.data.priority_sampler import PrioritySampler, reprioritize
from memrl.dqn.config import check_train_config
from memrl.dqn.loop import Trainer
from memrl.errors import ConfigError
from tests.helpers import EVERY_STAGE, TINY, assert_kill_and_resume_is_exact, built_stage_buffer, tiny_mode
from tests.test_buffers import fake


def test_new_rows_get_the_largest_priority_and_updates_set_delta_plus_eps_to_alpha():
    s = PrioritySampler(10, alpha=0.5, beta=0.5)
    s.extend(torch.arange(4))
    assert s.state_dict()["priority"][:5].tolist() == [1.0, 1.0, 1.0, 1.0, 0.0]
    s.update_priority(torch.tensor([0, 2]), torch.tensor([3.999, -0.999], dtype=torch.float64))
    p = s.state_dict()["priority"]
    assert p[0].item() == pytest.approx(2.0, rel=1e-12) and p[2].item() == pytest.approx(1.0, rel=1e-12)
    s.extend(torch.tensor([4]))  # the largest so far: 2.0
    assert s.state_dict()["priority"][4].item() == pytest.approx(2.0, rel=1e-12)


def test_draws_and_weights_equal_the_hand_computation():
    rb = agent_buffer(capacity=50, batch_size=16, priority=0.5, priority_beta=0.4)
    rb.extend(fake(8, False))
    sampler = priority_sampler(rb)
    assert isinstance(sampler, PrioritySampler)
    deltas = torch.tensor([0.0, 1.0, 4.0, 9.0, 0.25, 0.0, 16.0, 2.25], dtype=torch.float64)
    sampler.update_priority(torch.arange(8), deltas)
    p = (deltas + 1e-3) ** 0.5
    torch.manual_seed(5)
    batch = rb.sample()
    torch.manual_seed(5)
    u = torch.rand(16, dtype=torch.float64) * p.sum()
    rows = torch.searchsorted(p.cumsum(0), u, right=True).clamp(max=7)
    assert batch["action"].tolist() == rows.tolist()  # fake(): the action numbers the row
    assert batch["index"].tolist() == rows.tolist()
    w = (8 * p[rows] / p.sum()) ** -0.4
    torch.testing.assert_close(batch["priority_weight"], (w / w.max()).float(), rtol=1e-6, atol=0)


def test_a_high_priority_row_is_drawn_in_proportion():
    torch.manual_seed(0)
    rb = agent_buffer(capacity=100, batch_size=64, priority=1.0)
    rb.extend(fake(100, False))
    sampler = priority_sampler(rb)
    sampler.update_priority(torch.arange(100), torch.full((100,), 1.0 - 1e-3, dtype=torch.float64))  # p = 1
    # row 42 at p = 99: P = 99 / 198
    sampler.update_priority(torch.tensor([42]), torch.tensor([99.0 - 1e-3], dtype=torch.float64))
    drawn = torch.cat([rb.sample()["action"] for _ in range(100)])
    share = (drawn == 42).float().mean().item()
    # 6,400 draws, P = 0.5: sd 0.00625; 6 sd allowed
    assert abs(share - 0.5) < 0.04


def test_mode_a_keeps_its_demo_count_and_weights_demos_at_the_agent_mean():
    torch.manual_seed(0)
    rb = PriorKnowledgeBuffer(fake(100, True), capacity=1000, demo_fraction=0.1, batch_size=32, priority=0.5)
    rb.extend(fake(300, False, start=10_000))
    batch = rb.sample()
    assert rb.last_demo_count == 3 and batch["is_demo"][:3].all() and not batch["is_demo"][3:].any()
    assert batch["index"][:3].tolist() == [-1, -1, -1]
    assert (batch["action"][3:] - 10_000).tolist() == batch["index"][3:].tolist()
    w = batch["priority_weight"]
    torch.testing.assert_close(w[:3], w[3:].mean().expand(3))
    batch.set("td_error", torch.arange(32, dtype=torch.float32).reshape(32, 1) ** 2)
    reprioritize(priority_sampler(rb), batch)  # demo rows keep none
    p = priority_sampler(rb).state_dict()["priority"]
    for item in range(3, 32):  # a row drawn twice keeps its last value
        row = int(batch["index"][item])
        last = max(i for i in range(3, 32) if int(batch["index"][i]) == row)
        assert p[row].item() == pytest.approx((last + 1e-3) ** 0.5, rel=1e-9)


def test_the_td_loss_is_the_weighted_mean_and_writes_the_td_errors(compose_cfg):
    from memrl.dqn.learner import Learner

    cfg = compose_cfg("train", TINY)
    learner = Learner(cfg.agent, network=cfg.network)
    torch.manual_seed(0)
    batch = fake(6, False)
    batch["pixels"] = torch.randint(0, 255, (6, 4, 84, 84), dtype=torch.uint8)
    batch["next", "pixels"] = torch.randint(0, 255, (6, 4, 84, 84), dtype=torch.uint8)
    batch["action"] = torch.tensor([0, 3, 8, 1, 4, 4])
    batch["next", "reward"] = torch.arange(6, dtype=torch.float32).reshape(6, 1)
    plain = learner.loss(batch.clone())  # no weights: the mean of 1/2 delta^2
    sq = batch.clone()
    learner.loss(sq)
    delta2 = sq["td_error"].reshape(-1)
    torch.testing.assert_close(plain, 0.5 * delta2.mean(), rtol=1e-5, atol=0)
    w = torch.tensor([1.0, 0.5, 0.25, 1.0, 0.1, 0.8])
    weighted = batch.clone()
    weighted["priority_weight"] = w
    torch.testing.assert_close(learner.loss(weighted), 0.5 * (w * delta2).sum() / w.sum(), rtol=1e-5, atol=0)


def test_bad_values_are_refused(compose_cfg):
    with pytest.raises(ValueError, match="alpha"):
        PrioritySampler(10, alpha=0.0, beta=0.5)
    with pytest.raises(ConfigError, match=r"config 'buffer.priority': must be in \[0, 1\], got 1.5"):
        check_train_config(compose_cfg("train", ["buffer.priority=1.5"]))
    with pytest.raises(ConfigError, match="'buffer.priority': prioritized replay and"):
        check_train_config(compose_cfg("train", ["buffer.priority=0.5", "buffer.crash_share=0.1"]))
    with pytest.raises(ConfigError, match="config 'mode.sampling': prioritized replay keeps"):
        check_train_config(compose_cfg("train", ["+mode=A", "mode.sampling=proportional",
                                                 "buffer.priority=0.5"]))


@pytest.mark.parametrize("mode, stage, overrides", EVERY_STAGE)
def test_every_agent_stage_samples_through_the_priority_sampler(compose_cfg, demos, mode, stage, overrides):
    rb = built_stage_buffer(compose_cfg, demos, mode, stage, ["buffer.priority=0.5", *overrides])
    sampler = priority_sampler(rb)
    if stage == "B1":  # prior knowledge alone: sampled uniformly
        assert sampler is None
    else:
        assert isinstance(sampler, PrioritySampler) and sampler.alpha == 0.5


@pytest.mark.parametrize("mode", [None, "A"])
def test_prioritized_run_killed_and_resumed_equals_an_uninterrupted_one(
        compose_cfg, tmp_path, demos, monkeypatch, mode):
    extra = ["env.num_envs=4", "total_episodes=12", "checkpoint_every=3", "buffer.priority=0.5",
             *tiny_mode(mode)]
    cfg, full = assert_kill_and_resume_is_exact(compose_cfg, tmp_path, demos, monkeypatch, extra)
    assert full.updates > 0
    priorities = []
    for i, run in enumerate((tmp_path / "full", tmp_path / "cut")):
        trainer = Trainer(cfg, tmp_path / f"prio_{i}", demos)
        trainer.resume(run)
        priorities.append(priority_sampler(trainer.stage.buffer).state_dict())
    assert torch.equal(priorities[0]["priority"], priorities[1]["priority"])
    assert priorities[0]["max"] == priorities[1]["max"] > 1.0  # the TD errors were written back
