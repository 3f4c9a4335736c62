"""Advantage learning (``agent.advantage_learning``): the TD target against a hand computation,
the greedy action's target left as it is, every stage built with it, bad values refused."""

from __future__ import annotations

import pytest
import torch

from memrl.data.priority_sampler import TD_KEY
from memrl.dqn.config import AgentConfig, check_train_config
from memrl.dqn.learner import Learner
from memrl.errors import ConfigError
from memrl.losses import TDTerm, target_action_gap
from tests.helpers import EVERY_STAGE, TINY, tiny_mode
from tests.test_learner import batch


def moved_learner() -> Learner:
    """float32 throughout, online and target networks apart after one update."""
    torch.manual_seed(0)
    learner = Learner(AgentConfig(gamma=0.95, target_update_interval=10_000, precision="float32"))
    learner.update(batch(seed=1))
    return learner


def hand_loss(learner: Learner, td, alpha: float) -> torch.Tensor:
    """0.5 mean (r + 0.95 Q_t(s', argmax Q(s')) [not terminated]
    - alpha (max Q_t(s) - Q_t(s, a)) - Q(s, a))^2, every Q by a separate forward."""
    with torch.no_grad():
        a = td["action"][:, None]
        q = learner.qnet(td["pixels"]).gather(-1, a).squeeze(-1)
        a_star = learner.qnet(td["next", "pixels"]).argmax(-1, keepdim=True)
        with learner.loss_module.target_value_network_params.to_module(learner.loss_module.value_network):
            next_target = learner.qnet(td["next", "pixels"])
            here_target = learner.qnet(td["pixels"])
        gap = here_target.max(-1).values - here_target.gather(-1, a).squeeze(-1)
        not_terminal = (~td["next", "terminated"]).float().squeeze(-1)
        bootstrap = next_target.gather(-1, a_star).squeeze(-1)
        target = td["next", "reward"].squeeze(-1) + 0.95 * not_terminal * bootstrap - alpha * gap
        return 0.5 * ((target - q) ** 2).mean()


def test_the_target_is_lowered_by_alpha_times_the_target_networks_action_gap():
    learner = moved_learner()
    td = batch(seed=2)
    reward = td["next", "reward"].clone()
    q = learner.q_functions(td)
    with torch.no_grad():
        got = TDTerm(advantage=0.9)(td, q)
    expected = hand_loss(learner, td, 0.9)
    plain = hand_loss(learner, td, 0.0)
    assert not torch.allclose(expected, plain)  # the correction matters on this batch
    # float32 sums of 9 values, one forward each way: a few ulps of Q values around 0.1
    assert torch.allclose(got, expected, rtol=1e-5, atol=1e-6), (got, expected)
    assert torch.equal(td["next", "reward"], reward)  # the batch keeps its reward
    # the AL TD errors, for priorities: their half mean is the term
    assert q.td_error.shape == (6, 1) and torch.allclose(0.5 * q.td_error.mean(), got, rtol=1e-6)
    learner.loss(td)  # the learner puts them where prioritized replay reads them
    assert TD_KEY in td.keys() and td[TD_KEY].shape == (6, 1)


def test_the_greedy_actions_target_is_eq_1s():
    learner = moved_learner()
    td = batch(seed=2)
    with torch.no_grad(), learner.loss_module.target_value_network_params.to_module(
            learner.loss_module.value_network):
        td["action"] = learner.qnet(td["pixels"]).argmax(-1)
    assert torch.equal(target_action_gap(td, learner.q_functions(td)), torch.zeros(6))
    with torch.no_grad():
        assert torch.equal(TDTerm(advantage=0.9)(td, learner.q_functions(td)),
                           TDTerm()(td, learner.q_functions(td)))


def test_the_gap_is_nonnegative_and_zero_alpha_is_eq_1():
    learner = moved_learner()
    td = batch(seed=3)
    gap = target_action_gap(td, learner.q_functions(td))
    assert gap.shape == (6,) and bool((gap >= 0).all()) and bool((gap > 0).any())
    with torch.no_grad():
        got = TDTerm(advantage=0.0)(td, learner.q_functions(td))
    assert torch.allclose(got, hand_loss(learner, td, 0.0), rtol=1e-5, atol=1e-6)


def test_an_update_with_advantage_learning_moves_the_weights_through_the_learner():
    learner = moved_learner()
    learner.start_stage((TDTerm(advantage=0.9),))
    before = [p.detach().clone() for p in learner.qnet.parameters()]
    loss = learner.update(batch(seed=4))
    assert loss > 0 and learner.updates == 2
    assert any(not torch.equal(b, p) for b, p in zip(before, learner.qnet.parameters(), strict=True))


def test_a_learner_without_terms_takes_alpha_from_its_config():
    assert Learner(AgentConfig(advantage_learning=0.9)).terms == (TDTerm(advantage=0.9),)
    assert Learner(AgentConfig()).terms == (TDTerm(),)


@pytest.mark.parametrize("mode, stage, overrides", EVERY_STAGE)
def test_every_stage_is_built_with_the_configured_alpha(compose_cfg, demos, mode, stage, overrides):
    from memrl.dqn.builder import StageInputs, build_stage
    from memrl.modes import mode_of

    cfg = compose_cfg("train", TINY + tiny_mode(mode) + overrides + ["agent.advantage_learning=0.9"])
    built = build_stage(mode_of(cfg).stage(stage), StageInputs.of(cfg), demos, 1, torch.device("cpu"))
    assert built.terms[0] == TDTerm(advantage=0.9)


@pytest.mark.parametrize("alpha", ["1.0", "-0.1"])
def test_alpha_outside_0_1_is_refused_naming_the_key(compose_cfg, alpha):
    cfg = compose_cfg("train", TINY + [f"agent.advantage_learning={alpha}"])
    with pytest.raises(ConfigError, match="agent.advantage_learning"):
        check_train_config(cfg)


def test_a_short_run_with_advantage_learning_trains(compose_cfg, tmp_path, demos):
    from memrl.train import train

    cfg = compose_cfg("train", TINY + ["agent.advantage_learning=0.9"])
    summary = train(cfg, tmp_path / "run", demos=demos)
    assert summary.updates > 0
