"""Value heads that own their TD error: C51 (``network=c51``) and HL-Gauss (``network=hlgauss``).

Their targets against hand computations (mass kept, the mean moved by the reward and the
discount, clipped at the support's ends, no bootstrap on a crash, a bootstrap on a time
limit), each head trained through every path (n-step, margin, priorities, stage 1), killed and
resumed exactly, loaded back from its own ``final.pt`` by evaluate, deploy and the opponent
pool; bad values refused in one line."""

from __future__ import annotations

import math
from dataclasses import dataclass

import pytest
import torch

from memrl.dqn.config import AgentConfig
from memrl.dqn.learner import Learner
from memrl.modules.categorical import C51Term, CategoricalQNetwork, bootstrap, project, return_bounds
from memrl.modules.hlgauss import HLGaussQNetwork, HLGaussTerm, gauss_histogram
from memrl.modules.qnet import QNetwork, build_qnet, network_for_task
from tests.helpers import assert_kill_and_resume_is_exact, tiny_mode
from tests.test_learner import batch
from tests.test_network import assert_loads_back_everywhere, fixed_input

C51 = {"_target_": "memrl.modules.categorical.CategoricalQNetwork", "atoms": 11, "v_min": -20.0,
       "v_max": 20.0}
HLGAUSS = {"_target_": "memrl.modules.hlgauss.HLGaussQNetwork", "atoms": 20, "v_min": -20.0,
           "v_max": 20.0, "sigma": 0.75}


def moved_learner(network: dict) -> Learner:
    """float32 throughout, online and target networks apart after one update."""
    torch.manual_seed(0)
    learner = Learner(AgentConfig(gamma=0.95, target_update_interval=10_000, precision="float32"),
                      network=network)
    learner.update(batch(seed=1))
    return learner


# ------------------------------------------------------------------------------ C51's projection
def test_the_projection_splits_each_mass_between_its_two_nearest_points():
    support = torch.tensor([-2.0, -1.0, 0.0, 1.0, 2.0])
    probs = torch.tensor([[0.1, 0.2, 0.3, 0.25, 0.15]])
    # r = 0.5, gamma = 0.5: Tz = -0.5, 0, 0.5, 1, 1.5 -> by hand (half of -0.5 to -1 and half to
    # 0, all of 0 to 0, half of 0.5 to 0 and 1, all of 1 to 1, half of 1.5 to 1 and 2)
    got = project(support, 0.5 + 0.5 * support[None], probs)
    assert torch.allclose(got, torch.tensor([[0.0, 0.05, 0.4, 0.475, 0.075]]), atol=1e-7)
    assert torch.allclose(got.sum(-1), torch.ones(1), atol=1e-6)  # mass kept
    # the mean moved by the reward and the discount: 0.5 + 0.5 E[z] = 0.575
    mean = 0.5 + 0.5 * float((probs * support).sum())
    assert math.isclose(float((got * support).sum()), mean, abs_tol=1e-6)
    # clipped at the ends: every Tz above 2 lands on 2, below -2 on -2
    assert torch.equal(project(support, 3.0 + 0.5 * support[None], probs), torch.tensor([[0.0, 0, 0, 0, 1]]))
    assert torch.equal(project(support, -9.0 + support[None], probs), torch.tensor([[1.0, 0, 0, 0, 0]]))
    # no bootstrap (a crash): all the mass at r, split between its neighbours
    point = project(support, torch.full((1, 5), 0.25), probs)
    assert torch.allclose(point, torch.tensor([[0, 0, 0.75, 0.25, 0]]))


def hand_projection(support: list[float], values: list[float], probs: list[float]) -> list[float]:
    """C51's projection as Bellemare et al. (2017) write it: floor and ceil of each b_j."""
    lo, hi, k = support[0], support[-1], len(support)
    dz = (hi - lo) / (k - 1)
    m = [0.0] * k
    for v, p in zip(values, probs, strict=True):
        b = (min(max(v, lo), hi) - lo) / dz
        low, up = math.floor(b), math.ceil(b)
        if low == up:
            m[low] += p
        else:
            m[low] += p * (up - b)
            m[up] += p * (b - low)
    return m


def test_the_c51_target_is_the_projected_double_dqn_distribution():
    learner = moved_learner(C51)
    td = batch(seed=2)
    q = learner.q_functions(td)
    term = C51Term(gamma=0.95)
    got = term.target(td, q)
    net = learner.qnet
    z = net.support.tolist()
    with torch.no_grad():
        a_star = net(td["next", "pixels"]).argmax(-1)  # online
        with learner.loss_module.target_value_network_params.to_module(learner.loss_module.value_network):
            p_next = torch.softmax(net.outputs(td["next", "pixels"])["logits"], -1)
    checked = 0
    for i in range(6):
        r = float(td["next", "reward"][i])
        crash = bool(td["next", "terminated"][i])  # items 0 and 3; item 1 hit the time limit
        gamma = 0.0 if crash else 0.95
        probs = p_next[i, a_star[i]].tolist()
        want = hand_projection(z, [r + gamma * zj for zj in z], probs)
        assert torch.allclose(got[i], torch.tensor(want), atol=1e-6), i
        assert math.isclose(float(got[i].sum()), 1.0, abs_tol=1e-5)
        if -20 <= r + gamma * z[0] and r + gamma * z[-1] <= 20:  # nothing clipped: the mean is
            checked += 1  # r + gamma E[z] (r alone after a crash)
            mean = r + gamma * sum(p * zj for p, zj in zip(probs, z, strict=True))
            assert math.isclose(float((got[i] * net.support).sum()), mean, abs_tol=1e-4), i
    assert checked >= 3
    assert not torch.allclose(got[1], got[0])  # the time limit bootstraps, the crash does not


def test_the_c51_term_is_the_cross_entropy_and_sets_the_td_errors():
    learner = moved_learner(C51)
    td = batch(seed=2)
    q = learner.q_functions(td)
    loss = C51Term(gamma=0.95)(td, q)
    target = C51Term(gamma=0.95).target(td, learner.q_functions(td))
    logits = learner.qnet.outputs(td["pixels"])["logits"][torch.arange(6), td["action"]]
    want = -(target * torch.log_softmax(logits, -1)).sum(-1).mean()
    assert torch.allclose(loss, want, rtol=1e-6)
    expected_q = learner.qnet(td["pixels"])[torch.arange(6), td["action"]]
    td_error = ((target * learner.qnet.support).sum(-1) - expected_q).pow(2)[:, None]
    assert torch.allclose(q.td_error, td_error.detach(), rtol=1e-5, atol=1e-6)
    assert torch.equal(q.batch_q, q.batch_outputs()["q"])  # kept for the margin term


# ------------------------------------------------------------------------------------- HL-Gauss
def test_the_gauss_histogram_is_the_normal_mass_of_each_bin():
    y = torch.tensor([0.3, -19.0, 25.0])
    got = gauss_histogram(y, -20.0, 20.0, 20, 1.5)
    edges = [-20.0 + 2.0 * i for i in range(21)]
    cdf = lambda x, mu: 0.5 * (1 + math.erf((x - mu) / (1.5 * math.sqrt(2))))  # noqa: E731
    for row, mu in zip(got, [0.3, -19.0, 20.0], strict=True):  # 25 is clipped to the top, 20
        total = cdf(edges[-1], mu) - cdf(edges[0], mu)
        want = [(cdf(edges[i + 1], mu) - cdf(edges[i], mu)) / total for i in range(20)]
        assert torch.allclose(row, torch.tensor(want), atol=1e-6)
        assert math.isclose(float(row.sum()), 1.0, abs_tol=1e-5)
    centres = torch.tensor([-19.0 + 2.0 * i for i in range(20)])
    assert math.isclose(float((got[0] * centres).sum()), 0.3, abs_tol=1e-3)  # inside: the mean is y


def test_the_hlgauss_target_is_the_scalar_double_dqn_target():
    learner = moved_learner(HLGAUSS)
    td = batch(seed=2)
    q = learner.q_functions(td)
    y = HLGaussTerm(gamma=0.95).scalar_target(td, q)
    net = learner.qnet
    with torch.no_grad():
        a_star = net(td["next", "pixels"]).argmax(-1)
        with learner.loss_module.target_value_network_params.to_module(learner.loss_module.value_network):
            nxt = net(td["next", "pixels"])[torch.arange(6), a_star]
    alive = (~td["next", "terminated"]).float().reshape(-1)
    assert torch.allclose(y, td["next", "reward"].reshape(-1) + 0.95 * alive * nxt, atol=1e-6)
    assert torch.equal(y[[0, 3]], td["next", "reward"].reshape(-1)[[0, 3]])  # crashes: r alone
    loss = HLGaussTerm(gamma=0.95)(td, q)
    hist = gauss_histogram(y, -20.0, 20.0, 20, 0.75 * 2.0)
    logits = net.outputs(td["pixels"])["logits"][torch.arange(6), td["action"]]
    assert torch.allclose(loss, -(hist * torch.log_softmax(logits, -1)).sum(-1).mean(), rtol=1e-6)
    q_sa = net(td["pixels"])[torch.arange(6), td["action"]]
    assert torch.allclose(q.td_error.reshape(-1), (y - q_sa).pow(2), rtol=1e-5, atol=1e-6)


def test_the_support_comes_from_the_tasks_return_bounds(compose_cfg):
    cfg = compose_cfg("train", ["network=c51"])
    assert cfg.network.v_min is None and cfg.network.v_max is None
    lo, hi = return_bounds(cfg.env, 0.95)
    horizon = (1 - 0.95 ** 300) / 0.05  # Table II: a step between -1 - 2 and 1 + 1, a crash -5 once
    assert math.isclose(lo, -3 * horizon - 5) and math.isclose(hi, 2 * horizon)
    net = build_qnet(network_for_task(cfg.network, cfg.env, 0.95))
    assert (net.v_min, net.v_max) == (lo, hi) and net.arch["v_min"] == lo
    assert torch.allclose(net.support, torch.linspace(lo, hi, 51))
    hl = build_qnet(network_for_task(compose_cfg("train", ["network=hlgauss"]).network, cfg.env, 0.95))
    width = (hi - lo) / 51
    assert torch.allclose(hl.support, lo + width * (torch.arange(51) + 0.5))


# ------------------------------------------------------------------- trained, resumed, loaded back
RESUMABLE = ["env.num_envs=4", "total_episodes=12", "checkpoint_every=3"]
"""Killed after 8 of 12 episodes on 4 envs, a checkpoint every 3 (as the other resume tests)."""
HEADS = {
    # C51 in mode A: the margin term on expected values, 3-step returns, prioritized replay
    "c51": (["network=c51", *tiny_mode("A"), "agent.n_step=3", "buffer.priority=0.6"], CategoricalQNetwork),
    # HL-Gauss in mode B: stage 1 on demos (stage1.pt), then stage 2
    "hlgauss": (["network=hlgauss", *tiny_mode("B")], HLGaussQNetwork),
}


@pytest.mark.parametrize("name", list(HEADS))
def test_each_head_trains_resumes_exactly_and_loads_back_everywhere(compose_cfg, tmp_path, demos,
                                                                   monkeypatch, name):
    from memrl.checkpoint import load_stage1_qnet

    overrides, cls = HEADS[name]
    cfg, full = assert_kill_and_resume_is_exact(compose_cfg, tmp_path, demos, monkeypatch,
                                                [*RESUMABLE, *overrides])
    assert full.updates > 0
    run = tmp_path / "full"
    stored = torch.load(run / "checkpoints" / "final.pt", weights_only=False)
    trained = build_qnet(stored["network"]).eval()
    trained.load_state_dict(stored["qnet"])
    assert type(trained) is cls and trained.arch == stored["network"]
    assert stored["network"]["v_min"] == return_bounds(cfg.env, float(cfg.agent.gamma))[0]
    assert trained(fixed_input()).shape == (5, 9)
    assert_loads_back_everywhere(compose_cfg, run, trained, cls)
    if name == "hlgauss":
        assert type(load_stage1_qnet(run)) is cls


# --------------------------------------------------------------------------------------- refusals
@pytest.mark.parametrize(("overrides", "message"), [
    (["network=c51", "network.atoms=1"], "config 'network.atoms': must be >= 2, got 1"),
    (["network=c51", "network.v_min=5", "network.v_max=1"], "config 'network.v_min': must be below"),
    (["network=c51", "network.v_min=2", "network.v_max=2"], "config 'network.v_min': must be below"),
    (["network=hlgauss", "network.sigma=0"], "config 'network.sigma': must be > 0, got 0"),
    (["network=hlgauss", "network.sigma=-1"], "config 'network.sigma': must be > 0, got -1"),
    (["network=c51", "network.atoms=many"], "config 'network.atoms': "),
    (["network=c51", "+network.atom=3"], "config 'network.atom': CategoricalConfig has no such key"),
    (["network=c51", "agent.advantage_learning=0.5"], "config 'agent.advantage_learning': "
                                                      "CategoricalQNetwork has no advantage-learning"),
])
def test_bad_head_values_are_refused_at_start_naming_the_key(compose_cfg, overrides, message):
    from memrl.errors import one_line
    from memrl.schemas import check_train

    with pytest.raises(ValueError) as info:
        check_train(compose_cfg("train", overrides))
    line = one_line(info.value)
    assert line.startswith(message) and "\n" not in line, line


@pytest.mark.parametrize(("name", "cls"), [("c51", CategoricalQNetwork), ("hlgauss", HLGaussQNetwork)])
def test_a_head_yaml_lists_its_classs_keys_at_their_schema_defaults(name, cls):
    """The yaml lists the keys that ``network_keys`` lacks (so they take overrides without
    ``+``), each at its schema default: the defaults stay the schema's, nothing to drift."""
    import dataclasses

    import yaml
    from omegaconf import OmegaConf

    from memrl.config_reference import CONF_DIR
    from memrl.modules.network_config import NetworkConfig

    raw = yaml.safe_load((CONF_DIR / "network" / f"{name}.yaml").read_text())
    assert raw.pop("defaults") == ["network_keys", "_self_"]
    assert raw.pop("_target_") == f"{cls.__module__}.{cls.__qualname__}"
    base = {f.name for f in dataclasses.fields(NetworkConfig)}
    own = {k: v for k, v in OmegaConf.to_container(OmegaConf.structured(cls.config_schema)).items()
           if k not in base}
    assert raw == own


def test_the_configuration_reference_lists_every_networks_keys():
    from memrl.config_reference import CONF_DIR, markdown

    text = markdown()
    for path in (CONF_DIR / "network").glob("*.yaml"):
        assert f"### train network={path.stem}\n" in text, path.stem
    for key in ("atoms", "v_min", "v_max", "sigma"):
        assert f"| `network.{key}` |" in text, key


# ------------------------------------------------------------- a toy head from this file alone
class HuberQNetwork(QNetwork):
    """A toy value head declared here: Table I trained on the Huber loss of eq. (1)'s error."""

    @classmethod
    def td_term(cls, agent):
        return HuberTerm(gamma=float(agent.gamma))


@dataclass(frozen=True)
class HuberTerm:
    """Huber (smooth L1) of ``r + gamma^m Q_target(s', argmax Q(s')) - Q(s, a)``."""

    gamma: float
    name: str = "huber"

    def __call__(self, batch, q):
        a = batch["action"].reshape(-1, 1)
        values = q.batch_outputs()["q"].gather(-1, a).squeeze(-1)
        with torch.no_grad():
            nxt_pixels = batch["next", "pixels"]
            nxt = q.target(nxt_pixels)["q"].gather(-1, q.greedy(nxt_pixels)[:, None])
            reward, discount = bootstrap(batch, self.gamma)
            y = reward + discount * nxt.squeeze(-1)
            q.td_error = (y - values.detach()).pow(2)[:, None]
        return torch.nn.functional.smooth_l1_loss(values, y)


def test_a_toy_head_from_this_file_trains_with_its_own_term_and_resumes_exactly(
        compose_cfg, tmp_path, demos, monkeypatch):
    from memrl.dqn.loop import Trainer

    head = ["network._target_=tests.test_value_heads.HuberQNetwork", *tiny_mode("A")]
    cfg, full = assert_kill_and_resume_is_exact(compose_cfg, tmp_path, demos, monkeypatch,
                                                [*RESUMABLE, *head])
    assert full.updates > 0
    trainer = Trainer(cfg, tmp_path / "probe", demos)
    trainer.resume(tmp_path / "full")
    assert type(trainer.learner.qnet) is HuberQNetwork
    assert [t.name for t in trainer.learner.terms] == ["huber", "margin"]
    stored = torch.load(tmp_path / "full" / "checkpoints" / "final.pt", weights_only=False)
    assert stored["network"]["_target_"] == "tests.test_value_heads.HuberQNetwork"


def test_a_stages_head_td_is_the_networks_own_term(compose_cfg, demos):
    from memrl.dqn.builder import StageInputs, build_stage
    from memrl.losses import MarginTerm, TDTerm
    from memrl.modes import HEAD_TD, MODES, ModeSpec, StageSpec

    cfg = compose_cfg("train", ["+experiment=smoke", "network=c51", "+mode=A", "agent.gamma=0.9"])
    stage = build_stage(MODES["A"].stage("A"), StageInputs.of(cfg), demos, 1, torch.device("cpu"))
    assert stage.terms == (C51Term(gamma=0.9), MarginTerm(3.0, 0.8))
    assert MODES["A"].stage("A").terms(cfg.mode)[0] is HEAD_TD
    table1 = compose_cfg("train", ["+experiment=smoke", "+mode=A"])
    cpu = torch.device("cpu")
    assert build_stage(MODES["A"].stage("A"), StageInputs.of(table1), demos, 1, cpu).terms[0] == TDTerm()
    # a stage that lists no HEAD_TD trains on its other terms alone
    margin_only = ModeSpec("x", "X", (StageSpec("x1", terms=lambda c: (MarginTerm(1.0),)),), object).stages[0]
    assert build_stage(margin_only, StageInputs.of(table1), demos, 1, cpu).terms == (MarginTerm(1.0),)
