"""The crash-risk critic (``network=risk``, :mod:`memrl.modules.risk`): its target against a
hand computation, the safe choice of action, its term on a learner, and a run that trains,
resumes exactly and acts through the critic wherever the agent acts."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from memrl.dqn.config import AgentConfig
from memrl.dqn.learner import Learner
from memrl.modules.qnet import TDTerm
from memrl.modules.risk import RiskQNetwork, RiskTerm, risk_target, safe_choice
from tests.helpers import assert_kill_and_resume_is_exact
from tests.test_learner import batch
from tests.test_network import fixed_input

RISK = {"_target_": "memrl.modules.risk.RiskQNetwork", "gamma": 0.9, "threshold": 0.3,
        "base": {"_target_": "memrl.modules.qnet.QNetwork"}}


def short_episode() -> TensorDict:
    """Four transitions: a lane change (ongoing), a 3-step window (ongoing), a time limit
    (truncated, not terminated) and a crash (terminated)."""
    return TensorDict({
        "steps_to_next_obs": torch.tensor([[1], [3], [1], [1]]),
        "next": TensorDict({"terminated": torch.tensor([[False], [False], [False], [True]]),
                            "truncated": torch.tensor([[False], [False], [True], [False]])}, [4]),
    }, [4])


def test_the_risk_target_is_one_at_a_crash_and_discounted_otherwise():
    next_risk = torch.tensor([0.5, 0.5, 0.2, 0.7])
    y = risk_target(short_episode(), next_risk, gamma=0.9)
    # lane change: 0.9 * 0.5; 3-step window: 0.9^3 * 0.5; time limit bootstraps: 0.9 * 0.2;
    # crash: 1 whatever the next state's risk (no bootstrap past it)
    assert torch.allclose(y, torch.tensor([0.45, 0.3645, 0.18, 1.0]), rtol=0, atol=1e-7)


def test_the_safe_choice_is_the_best_allowed_action_else_the_least_risk_one():
    q = torch.tensor([[5.0, 3.0, 1.0], [5.0, 3.0, 1.0], [0.0, 9.0, 2.0]])
    risk = torch.tensor([[0.9, 0.05, 0.1], [0.9, 0.5, 0.6], [0.1, 0.1, 0.1]])
    values = safe_choice(q, risk, threshold=0.1)
    # row 0: actions 1 and 2 allowed, 1 has the higher Q (the best action 0 is too risky);
    # row 1: none allowed, action 1 has the least risk; row 2: all allowed, argmax Q
    assert values.argmax(-1).tolist() == [1, 1, 1]
    assert values[0].tolist() == [-math.inf, 3.0, 1.0]
    assert torch.equal(values[1], -risk[1])


def moved_learner(network: dict, **agent) -> Learner:
    torch.manual_seed(0)
    learner = Learner(AgentConfig(gamma=0.95, target_update_interval=10_000, precision="float32", **agent),
                      network=network)
    first = batch(seed=1)
    if network.get("task_action") == "proposed":
        first["task_action"] = first["action"].clone()
    learner.update(first)  # online and target apart
    return learner


@pytest.mark.parametrize("bootstrap", ["policy", "safest"])
def test_the_risk_term_is_the_base_td_term_plus_the_critics_cross_entropy(bootstrap):
    learner = moved_learner({**RISK, "bootstrap": bootstrap, "weight": 2.0})
    [term] = learner.terms
    assert term == RiskTerm(base=TDTerm(), gamma=0.9, weight=2.0, bootstrap=bootstrap)
    net: RiskQNetwork = learner.qnet
    b = batch(seed=2)
    with torch.no_grad():
        total = float(learner.loss(b.clone()))
        base = float(TDTerm()(b.clone(), learner.q_functions(b.clone()).view(net.base)))
        q = learner.q_functions(b)
        nxt = b["next", "pixels"]
        with q.target_params():
            target = torch.sigmoid(net.critic(nxt))
        if bootstrap == "safest":
            a_next = target.argmin(-1)
        else:  # the online networks' safe choice
            a_next = safe_choice(net.base(nxt), torch.sigmoid(net.critic(nxt)), 0.3).argmax(-1)
        r_next = target[torch.arange(len(b)), a_next]
        crash = b["next", "terminated"].reshape(-1)
        y = torch.where(crash, torch.ones_like(r_next), 0.9 * r_next)  # 1-step batch
        p = torch.sigmoid(net.critic(b["pixels"]))[torch.arange(len(b)), b["action"].reshape(-1)]
        bce = -(y * torch.log(p) + (1 - y) * torch.log(1 - p)).mean()
    assert crash.any() and not crash.all()
    assert total == pytest.approx(base + 2.0 * float(bce), rel=1e-5)


def test_a_task_head_that_learns_from_its_proposals_takes_task_action_and_the_critic_the_executed():
    learner = moved_learner({**RISK, "task_action": "proposed"})
    [term] = learner.terms
    assert term.task_action == "proposed"
    net: RiskQNetwork = learner.qnet
    b = batch(seed=2)
    b["task_action"] = (b["action"] + 1 + torch.arange(len(b)).reshape(b["action"].shape) % 3) % 9
    assert bool((b["task_action"] != b["action"]).all())
    proposed = b.clone().set("action", b["task_action"].clone())
    with torch.no_grad():
        total = float(learner.loss(b.clone()))
        on_proposed = learner.q_functions(proposed.clone())
        base_proposed = float(TDTerm()(proposed.clone(), on_proposed.view(net.base)))
        base_executed = float(TDTerm()(b.clone(), learner.q_functions(b.clone()).view(net.base)))
        q = learner.q_functions(b)
        bce = float(term(b.clone(), q)) - base_proposed  # the critic's part, on whichever action
        with q.target_params():
            target = torch.sigmoid(net.critic(b["next", "pixels"]))
        a_next = safe_choice(net.base(b["next", "pixels"]), torch.sigmoid(net.critic(b["next", "pixels"])),
                             0.3).argmax(-1)
        y = torch.where(b["next", "terminated"].reshape(-1), torch.tensor(1.0),
                        0.9 * target[torch.arange(len(b)), a_next])
        p = torch.sigmoid(net.critic(b["pixels"]))[torch.arange(len(b)), b["action"].reshape(-1)]
        executed_bce = float(-(y * torch.log(p) + (1 - y) * torch.log(1 - p)).mean())
    assert base_proposed != pytest.approx(base_executed, rel=1e-3)  # the two actions' TD terms differ
    assert total == pytest.approx(base_proposed + executed_bce, rel=1e-5)
    assert bce == pytest.approx(executed_bce, rel=1e-4)
    with pytest.raises(KeyError, match="has no 'task_action'"):
        learner.loss(batch(seed=2))


@pytest.mark.parametrize("eps", [0.0, 1.0])
def test_the_acting_loop_stores_the_task_heads_proposal_beside_the_masked_action(compose_cfg, tmp_path, eps):
    from memrl.dqn.loop import Trainer
    from tests.helpers import TINY

    cfg = compose_cfg("train", [*TINY, "network=risk", "network.task_action=proposed",
                                "network.threshold=0.5", "agent.precision=float32",
                                f"agent.eps_start={eps}", f"agent.eps_end={eps}"])
    trainer = Trainer(cfg, tmp_path / "run")
    net: RiskQNetwork = trainer.rounds.acting_net.module[0].module.net  # the acting copy (overlap mode)
    x = fixed_input()
    with torch.no_grad():
        greedy = net.base(x).argmax(-1)
        torch.nn.init.constant_(net.critic.head[-1].bias, 0.0)
        net.critic.head[-1].bias[greedy[0]] = 20.0  # the first stack's best task action: masked
        masked = net.decide(x).argmax(-1)
    td = TensorDict({"pixels": x}, [len(x)])
    trainer._act(td, frames=10_000)  # past the warm-up
    assert int(masked[0]) != int(greedy[0])
    if eps == 0:  # greedy: the task head proposed its best action, the mask's choice was executed
        assert torch.equal(td["action"], masked) and torch.equal(td["task_action"], greedy)
    else:  # every env explores: the one draw was proposed and executed
        assert torch.equal(td["task_action"], td["action"])
    td = TensorDict({"pixels": x}, [len(x)])
    trainer._act(td, frames=0)  # the warm-up's random actions: proposed as executed
    assert torch.equal(td["task_action"], td["action"])


def test_only_the_critic_learns_from_its_term_and_the_base_only_from_its_own():
    learner = moved_learner(RISK)
    net: RiskQNetwork = learner.qnet
    b = batch(seed=3)
    q = learner.q_functions(b)
    [term] = learner.terms
    view = q.view(net.base)
    learner.optimizer.zero_grad()
    term.base(b.clone(), view).backward()
    assert all(p.grad is None for p in net.critic.parameters())
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in net.base.parameters())


def test_the_agent_acts_through_the_critic_in_training_and_evaluation():
    from memrl.evaluation.policies import GreedyActor
    from memrl.modules.policy import GreedyPolicy

    learner = moved_learner({**RISK, "threshold": 0.5})
    net: RiskQNetwork = learner.qnet
    x = fixed_input()
    with torch.no_grad():
        torch.nn.init.constant_(net.critic.head[-1].bias, 0.0)
        net.critic.head[-1].bias[net.base(x)[0].argmax()] = 20.0  # the first stack's best action: risky
        decided = net.decide(x).argmax(-1)
        acted = learner.acting_actor(TensorDict({"pixels": x}, [len(x)]))["action"]
    assert torch.equal(acted, decided) and torch.equal(GreedyPolicy(net).act_batch(x), decided)
    actions, values = GreedyActor(net, gamma=0.95).act_values(x)  # the evaluation's recording actor
    assert torch.equal(actions, decided) and set(values) == {"q", "risk"}
    assert int(decided[0]) != int(net.base(x)[0].argmax())


@pytest.mark.parametrize("shared", [True, False])
def test_a_shared_trunk_critic_reads_the_base_convs_and_its_cross_entropy_trains_them(shared):
    from memrl.modules.qnet import build_qnet

    torch.manual_seed(0)
    net = build_qnet({**RISK, "shared_trunk": shared})
    x = fixed_input()
    convs = [m for m in net.critic.modules() if isinstance(m, torch.nn.Conv2d)]
    assert (len(convs) == 0) == shared  # shared: a hidden and an output layer on the base's convs
    logits = net.risk_logits(x)
    if shared:
        assert torch.equal(logits, net.critic(net.base.conv_features(x)))
    out = [m for m in net.critic.modules() if isinstance(m, torch.nn.Linear)][-1]
    assert float((out.bias.detach() - math.log(0.01 / 0.99)).abs().max()) < 1e-6  # the prior either way
    torch.nn.functional.binary_cross_entropy_with_logits(logits, torch.ones_like(logits)).backward()
    trained = [p.grad is not None and float(p.grad.abs().sum()) > 0 for p in net.base.features.parameters()]
    assert all(trained) if shared else not any(trained)
    assert all(p.grad is None for p in net.base.head.parameters())  # the task head's own layers: not


RESUMABLE = ["env.num_envs=4", "total_episodes=12", "checkpoint_every=3"]


@pytest.mark.parametrize("overrides", [
    ["network=risk"],
    # beside HL-Gauss, in mode A: the base's own term, the margin term on the demos
    ["network=risk", "network.base._target_=memrl.modules.hlgauss.HLGaussQNetwork",
     "+mode=A", "mode.example.episodes=2", "+network.base.atoms=11", "+network.base.v_min=null",
     "+network.base.v_max=null", "+network.base.sigma=0.75", "network.bootstrap=safest"],
    # on the base's conv trunk, no mask: the auxiliary crash-prediction task alone
    ["network=risk", "network.shared_trunk=true", "network.threshold=1.0"],
    # the task head learns from its proposals, in mode A (the demos get theirs) with ez_speed
    ["network=risk", "network.task_action=proposed", "network.threshold=0.02", "+mode=A",
     "mode.example.episodes=2", "agent.exploration=ez_speed"],
])
def test_a_risk_critic_run_trains_resumes_exactly_and_acts_safely_from_its_final_pt(
        compose_cfg, tmp_path, demos, monkeypatch, overrides):
    from memrl.checkpoint import LearnedCarController, load_policy, load_qnet

    cfg, full = assert_kill_and_resume_is_exact(compose_cfg, tmp_path, demos, monkeypatch,
                                                [*RESUMABLE, *overrides])
    assert full.updates > 0
    run = tmp_path / "full"
    net, _ = load_qnet(run)
    base = type(net.base)
    assert type(net) is RiskQNetwork and f"{base.__module__}.{base.__qualname__}" == cfg.network.base._target_
    assert net.gamma_risk == float(cfg.network.gamma)  # the evaluation's risk calibration reads it
    x = fixed_input()
    with torch.no_grad():
        decided = net.decide(x).argmax(-1)
    policy = load_policy(str(run))  # evaluate and deploy
    assert [policy.act(s.numpy()) for s in x] == decided.tolist()
    index = torch.zeros(len(x), dtype=torch.long)
    pool = LearnedCarController([str(run / "checkpoints" / "final.pt")])  # the opponent pool
    assert torch.equal(pool.q_values(index, x).argmax(-1), decided)


@pytest.mark.parametrize(("overrides", "message"), [
    (["network=risk", "network.threshold=0"], "config 'network.threshold': must be in (0, 1], got 0"),
    (["network=risk", "network.gamma=1"], "config 'network.gamma': must be in (0, 1), got 1"),
    (["network=risk", "network.bootstrap=future"],
     "config 'network.bootstrap': must be one of policy, safest"),
    (["network=risk", "network.base.channels=0"], "config 'network.base.channels': must be >= 1, got 0"),
    (["network=risk", "network.task_action=chosen"],
     "config 'network.task_action': must be one of executed, proposed"),
    (["network=risk", "network.task_action=proposed", "agent.exploration=boltzmann"],
     "config 'network.task_action': proposed needs the task head's own proposal"),
])
def test_bad_risk_values_are_refused_at_start_naming_the_key(compose_cfg, overrides, message):
    from memrl.errors import one_line
    from memrl.schemas import check_train

    with pytest.raises(ValueError) as info:
        check_train(compose_cfg("train", overrides))
    line = one_line(info.value)
    assert line.startswith(message) and "\n" not in line, line


def test_a_fresh_critic_allows_every_action_so_the_agent_acts_as_its_task_head():
    from memrl.modules.qnet import build_qnet

    net = build_qnet(RISK)
    x = fixed_input()
    with torch.no_grad():
        risk = torch.sigmoid(net.risk_logits(x))
        assert float((net.critic.head[-1].bias - math.log(0.01 / 0.99)).abs().max()) < 1e-6
        assert bool((risk < 0.3).all())  # below the threshold: every action allowed
        assert torch.equal(net.decide(x).argmax(-1), net.base(x).argmax(-1))


def test_stage_2_with_a_critic_starts_from_a_stage_1_trained_without_one(compose_cfg, tmp_path, demos):
    from omegaconf import open_dict

    from memrl.dqn.loop import Trainer
    from memrl.schemas import check_train
    from memrl.train import train
    from tests.helpers import tiny

    plain = compose_cfg("train", tiny("B"))
    train(plain, tmp_path / "plain", demos=demos)
    s1 = torch.load(tmp_path / "plain" / "checkpoints" / "stage1.pt", weights_only=False)["loss_module"]
    overrides = [*tiny("B"), "network=risk", f"mode.stage1.init={tmp_path / 'plain'}"]
    cfg = compose_cfg("train", overrides)
    check_train(cfg)  # the base head is the stored architecture: accepted
    fresh = Trainer(cfg, tmp_path / "fresh", demos).learner.loss_module.state_dict()
    trainer = Trainer(cfg, tmp_path / "risk", demos)
    trainer.run_offline()  # takes the shared stage 1
    assert trainer.counters.stage == "B2"
    now = trainer.learner.loss_module.state_dict()
    base = {k.replace(".module.base.", ".module."): v for k, v in now.items() if ".module.base." in k}
    assert base.keys() == {k for k in s1 if ".module.0.module." in k}
    online = {k: v for k, v in s1.items() if k.startswith("value_network")}
    # online and target (synced at the switch): the stage 1's online weights
    assert all(torch.equal(v, online[k.removeprefix("target_")]) for k, v in base.items())
    critic = [k for k in now if ".critic." in k]
    assert critic and all(torch.equal(now[k], fresh[k]) for k in critic)  # its own initial weights
    # a stage 1 of another architecture is refused, naming both
    with open_dict(cfg):
        cfg.network.base.hidden = 128
    with pytest.raises(ValueError, match=r"config 'mode.stage1.init': .*its network QNetwork\(\) is not "
                                         r"this run's RiskQNetwork\(.*\) nor its base head "
                                         r"QNetwork\(hidden=128\)"):
        check_train(cfg)
