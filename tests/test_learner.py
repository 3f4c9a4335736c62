"""The double-DQN loss against a hand computation, and the learner's update mechanics."""

from __future__ import annotations

import torch
from tensordict import TensorDict

from memrl.dqn.config import AgentConfig
from memrl.dqn.learner import Learner
from memrl.losses import MarginTerm, TDTerm


def batch(n: int = 6, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    px = lambda: torch.randint(0, 256, (n, 4, 84, 84), dtype=torch.uint8, generator=g)  # noqa: E731
    terminated = torch.tensor([True, False, False, True, False, False][:n]).unsqueeze(-1)
    truncated = torch.tensor([False, True, False, False, False, False][:n]).unsqueeze(-1)
    return TensorDict({
        "pixels": px(), "action": torch.randint(0, 9, (n,), generator=g),
        "is_demo": torch.zeros(n, dtype=torch.bool),
        "next": {"pixels": px(), "reward": torch.randn(n, 1, generator=g),
                 "terminated": terminated, "truncated": truncated,
                 "done": terminated | truncated},
    }, [n])


def test_loss_equals_hand_computed_half_squared_double_dqn_error():
    torch.manual_seed(0)
    learner = Learner(AgentConfig(gamma=0.95, target_update_interval=10_000))
    learner.update(batch(seed=1))  # online moves away from target: double DQN now matters
    td = batch(seed=2)
    with torch.no_grad():
        q = learner.qnet(td["pixels"]).gather(-1, td["action"][:, None]).squeeze(-1)
        next_online = learner.qnet(td["next", "pixels"])
        a_star = next_online.argmax(-1, keepdim=True)
        with learner.loss_module.target_value_network_params.to_module(learner.loss_module.value_network):
            next_target = learner.qnet(td["next", "pixels"])
        online_max = next_online.gather(-1, a_star).squeeze(-1)
        bootstrap = next_target.gather(-1, a_star).squeeze(-1)
        assert not torch.allclose(bootstrap, online_max)  # target and online differ
        not_terminal = (~td["next", "terminated"]).float().squeeze(-1)  # truncated still bootstraps
        target = td["next", "reward"].squeeze(-1) + 0.95 * not_terminal * bootstrap
        expected = 0.5 * ((target - q) ** 2).mean()
        got = learner.loss(td)
    assert torch.allclose(got, expected, rtol=1e-5, atol=1e-6), (got, expected)


def test_target_network_is_a_hard_copy_every_interval():
    torch.manual_seed(0)
    learner = Learner(AgentConfig(target_update_interval=3, lr=1e-3))
    online = learner.loss_module.value_network_params
    target = learner.loss_module.target_value_network_params

    def same() -> bool:
        return all(torch.equal(a, b) for a, b in zip(online.values(True, True),
                                                     target.values(True, True), strict=True))

    assert same()
    learner.update(batch())
    assert not same()
    learner.update(batch())
    learner.update(batch())
    assert same()


def test_actor_acts_with_the_updated_online_weights():
    torch.manual_seed(0)
    learner = Learner(AgentConfig(lr=1e-2))
    td = batch()
    before = learner.actor(td.clone())["action_value"].detach()
    learner.update(td)
    after = learner.actor(td.clone())["action_value"].detach()
    assert not torch.allclose(before, after)
    assert torch.allclose(after, learner.q_values(td["pixels"]))


def test_margin_loss_on_demo_items_matches_a_hand_computation():
    torch.manual_seed(0)
    learner = Learner(AgentConfig())
    td = batch()
    td["is_demo"] = torch.tensor([True, False, True, False, False, True])
    base = learner.loss(td).detach()
    learner.start_stage((TDTerm(), MarginTerm(2.0, 0.8)))
    with torch.no_grad():
        q = learner.qnet(td["pixels"][td["is_demo"]])
        a = td["action"][td["is_demo"]]
        bonus = torch.full_like(q, 0.8)
        bonus[torch.arange(3), a] = 0.0
        expected = (q + bonus).max(-1).values - q[torch.arange(3), a]
        got = learner.loss(td)
    assert (expected >= 0).all()
    assert torch.allclose(got, base + 2.0 * expected.mean(), atol=1e-6)


def test_pool_first_network_equals_table_i_order_exactly():
    from memrl.modules.qnet import QNetwork

    torch.manual_seed(0)
    literal, fast = QNetwork(pool_first=False), QNetwork(pool_first=True)
    fast.load_state_dict(literal.state_dict())  # same parameter names in both orders
    x = torch.randint(0, 256, (5, 4, 84, 84), dtype=torch.uint8)
    assert torch.equal(literal(x), fast(x))


def test_exploration_ignores_the_process_wide_deterministic_mode():
    """TorchRL losses set a process-wide deterministic exploration type while they run; the
    acting thread of overlap mode must keep exploring meanwhile."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from memrl.dqn.exploration import make_exploration

    explore = make_exploration(1.0, 1.0, 10)  # always random
    torch.manual_seed(0)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        actions = [int(explore(TensorDict({"action": torch.tensor(4)}, []))["action"])
                   for _ in range(50)]
    assert len(set(actions)) > 3
    greedy = make_exploration(0.0, 0.0, 10)
    assert int(greedy(TensorDict({"action": torch.tensor(4)}, []))["action"]) == 4
