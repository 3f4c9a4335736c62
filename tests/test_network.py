"""The ``network`` config group: Table I unchanged bit for bit, the dueling and LayerNorm
variants trained, saved with their architecture and loaded back by every loader; old files
load as Table I, mismatched files are refused naming the file."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml
from hydra.utils import instantiate
from torch import nn

from memrl.checkpoint import load_qnet, load_stage1_qnet, save_qnet
from memrl.checkpoint import resume as ckpt
from memrl.checkpoint.opponents import LearnedCarController
from memrl.deploy import deploy_config, make_policy
from memrl.dqn.config import AgentConfig
from memrl.dqn.learner import Learner
from memrl.errors import USAGE_EXIT
from memrl.modules.policy import GreedyPolicy
from memrl.modules.qnet import TABLE1, DuelingQNetwork, QNetwork, build_qnet
from memrl.train import train
from tests.helpers import TINY, tiny

ROOT = Path(__file__).resolve().parents[1]


class TodaysQNetwork(nn.Module):
    """``memrl.modules.qnet.QNetwork`` as it was before the network group (verbatim but for
    the name and the bf16 option): the reference of Table I's outputs and parameter names."""

    def __init__(self, frames: int = 4, size: int = 84, n_actions: int = 9,
                 channels: int = 16, hidden: int = 256, pool_first: bool = True) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        c_in = frames
        for _ in range(3):
            act_pool = [nn.MaxPool2d(2), nn.ReLU()] if pool_first else [nn.ReLU(), nn.MaxPool2d(2)]
            layers += [nn.Conv2d(c_in, channels, 3, padding=1), *act_pool]
            c_in = channels
        self.features = nn.Sequential(*layers)
        side = size
        for _ in range(3):
            side //= 2
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(channels * side * side, hidden), nn.ReLU(),
                                  nn.Linear(hidden, n_actions))

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        batch = pixels.shape[:-3]
        x = pixels.reshape(-1, *pixels.shape[-3:]).to(torch.float32).div_(255.0)
        return self.head(self.features(x)).reshape(*batch, -1)


def fixed_input(n: int = 5) -> torch.Tensor:
    g = torch.Generator().manual_seed(1234)
    return torch.randint(0, 256, (n, 4, 84, 84), dtype=torch.uint8, generator=g)


def equal_weights(a: nn.Module, b: nn.Module) -> bool:
    sa, sb = a.state_dict(), b.state_dict()
    return list(sa) == list(sb) and all(torch.equal(sa[k], sb[k]) for k in sa)


# ---------------------------------------------------------------------------------------------
# Table I unchanged


@pytest.mark.parametrize("pool_first", [True, False])
def test_table1_default_equals_todays_qnetwork_bit_for_bit(compose_cfg, pool_first):
    cfg = compose_cfg("train")
    assert cfg.network._target_ == "memrl.modules.qnet.QNetwork"
    torch.manual_seed(7)
    today = TodaysQNetwork(pool_first=pool_first)
    torch.manual_seed(7)
    net = build_qnet(cfg.network, pool_first=pool_first)
    assert type(net) is QNetwork and net.arch == TABLE1
    assert equal_weights(net, today)  # same names, same draws from the same seed
    x = fixed_input()
    assert torch.equal(net(x), today(x))
    # the learner's network, built from the same node, draws the same initial weights
    torch.manual_seed(7)
    learner = Learner(AgentConfig(pool_first=pool_first), network=cfg.network)
    assert equal_weights(learner.qnet, today)


@pytest.mark.parametrize("name", ["table1", "dueling"])
def test_network_files_name_their_class_and_repeat_no_schema_default(name):
    from omegaconf import OmegaConf

    from memrl.modules.network_config import NetworkConfig

    raw = yaml.safe_load((ROOT / "conf" / "network" / f"{name}.yaml").read_text())
    defaults = OmegaConf.to_container(OmegaConf.structured(NetworkConfig))
    assert raw.pop("defaults") == ["network_schema", "_self_"]
    assert raw["_target_"].startswith("memrl.modules.qnet.")
    assert not [k for k, v in raw.items() if defaults.get(k) == v]


def test_a_file_written_before_architectures_were_stored_loads_as_table1(tmp_path):
    torch.manual_seed(3)
    today = TodaysQNetwork()
    file = tmp_path / "final.pt"
    torch.save({"qnet": today.state_dict(), "env": {"duration": 30}}, file)  # the old format
    net, env = load_qnet(file)
    assert type(net) is QNetwork and net.arch == TABLE1 and env == {"duration": 30}
    x = fixed_input()
    assert torch.equal(net(x), today(x))
    # an old stage1.pt: a DQNLoss state and no architecture
    learner = Learner(AgentConfig())
    torch.save({"loss_module": learner.loss_module.state_dict(), "stage1": {}}, tmp_path / "stage1.pt")
    stage1 = load_stage1_qnet(tmp_path / "stage1.pt")
    assert type(stage1) is QNetwork and equal_weights(stage1, learner.qnet)


# ---------------------------------------------------------------------------------------------
# refusals


DUELING = {**TABLE1, "_target_": "memrl.modules.qnet.DuelingQNetwork"}


@pytest.mark.parametrize(("arch", "weights_of"), [(DUELING, QNetwork), (None, DuelingQNetwork),
                                                  ({**TABLE1, "layernorm": True}, QNetwork)],
                         ids=["dueling-arch-table1-weights", "no-arch-dueling-weights",
                              "layernorm-arch-table1-weights"])
def test_a_file_whose_architecture_does_not_match_its_weights_is_refused(tmp_path, arch, weights_of):
    file = tmp_path / "run" / "checkpoints" / "final.pt"
    file.parent.mkdir(parents=True)
    state = {"qnet": weights_of().state_dict(), "env": {}}
    if arch is not None:
        state["network"] = arch
    torch.save(state, file)
    with pytest.raises(ckpt.CheckpointError) as info:
        load_qnet(file)
    message = str(info.value)
    assert message.startswith(f"{file}: its weights do not match its network ") and "\n" not in message
    with pytest.raises(ckpt.CheckpointError, match="its weights do not match"):
        LearnedCarController([str(file)])


def cli(args: list[str], root: Path) -> subprocess.CompletedProcess:
    environ = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    environ.update(MEMRL_ROOT=str(root), SDL_VIDEODRIVER="dummy")
    return subprocess.run([sys.executable, "-m", *args], cwd=ROOT, env=environ,
                          capture_output=True, text=True, timeout=300)


def test_evaluate_refuses_a_mismatched_file_on_one_line_with_status_2(tmp_path):
    run = tmp_path / "run"
    file = run / "checkpoints" / "final.pt"
    file.parent.mkdir(parents=True)
    torch.save({"qnet": QNetwork().state_dict(), "network": DUELING, "env": {}}, file)
    proc = cli(["memrl.evaluate", f"policy.run={run}", "workers=1"], tmp_path)
    assert proc.returncode == USAGE_EXIT, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"error: {file}: its weights do not match its "
                                                   "network DuelingQNetwork()"), proc.stderr
    assert not (run / "eval").exists() and not list(tmp_path.rglob(".hydra"))


@pytest.mark.parametrize(("override", "message"), [
    ("network.hidden=0", "error: config 'network.hidden': must be >= 1, got 0"),
    ("network.channels=-1", "error: config 'network.channels': must be >= 1, got -1"),
    ("network._target_=memrl.modules.qnet.Nope", "error: config 'network._target_': cannot import"),
    ("network._target_=memrl.modules.qnet.TABLE1", "error: config 'network._target_': cannot import"),
])
def test_bad_network_values_are_refused_at_start(tmp_path, override, message):
    proc = cli(["memrl.train", override], tmp_path)
    assert proc.returncode == USAGE_EXIT, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith(message), proc.stderr
    assert not list(tmp_path.rglob(".hydra")) and not list(tmp_path.rglob("config.yaml"))


# ---------------------------------------------------------------------------------------------
# trained, saved and loaded back


ARCHS = {
    "table1": ([], QNetwork),
    "dueling": (["network=dueling", "+mode=B"], DuelingQNetwork),  # + stage1.pt, double DQN
    "layernorm": (["network.layernorm=true", "network.layernorm_convs=true"], QNetwork),
}


@pytest.mark.parametrize("name", list(ARCHS))
def test_a_trained_network_loads_back_through_evaluate_deploy_and_the_pool(
        compose_cfg, tmp_path, demos, name):
    overrides, cls = ARCHS[name]
    cfg = compose_cfg("train", TINY + overrides)
    run = tmp_path / "run"
    summary = train(cfg, run, demos=demos)
    assert summary.updates > 0
    # the trained network, rebuilt from the config as a resume does (strict weights)
    state = ckpt.load_state(ckpt.find(run), cfg)
    learner = Learner(cfg.agent, network=cfg.network)
    learner.load_state_dict(state["learner"])
    trained = build_qnet(cfg.network).eval()
    trained.load_state_dict(learner.qnet.state_dict())  # float32, contiguous
    assert type(trained) is cls
    stored = torch.load(run / "checkpoints" / "final.pt", weights_only=False)["network"]
    assert stored == trained.arch and stored["_target_"] == f"memrl.modules.qnet.{cls.__name__}"
    assert_loads_back_everywhere(compose_cfg, run, trained, cls)
    # a resume into a fresh trainer rebuilds the same network from the run's config
    from memrl.dqn.loop import Trainer

    resumed = Trainer(cfg, tmp_path / "probe", demos)
    resumed.resume(run)
    assert type(resumed.learner.qnet) is cls and equal_weights(resumed.learner.qnet, trained)
    if name == "dueling":  # mode B: stage1.pt stores the architecture too
        s1 = torch.load(run / "checkpoints" / "stage1.pt", weights_only=False)
        assert s1["network"] == trained.arch
        at_switch = Learner(cfg.agent, network=cfg.network)
        at_switch.loss_module.load_state_dict(s1["loss_module"])
        ref = build_qnet(cfg.network).eval()
        ref.load_state_dict(at_switch.qnet.state_dict())
        x = fixed_input()
        assert torch.equal(load_stage1_qnet(run)(x), ref(x))
        # a Table I run may not resume it, nor start stage 2 from its stage 1
        table1 = compose_cfg("train", tiny("B"))
        with pytest.raises(ckpt.CheckpointError, match="network._target_"):
            ckpt.load_state(ckpt.find(run), table1)
        from memrl.schemas import check_train

        with pytest.raises(ValueError, match=r"config 'mode.stage1.init': .*stage1.pt: its network "
                                             r"DuelingQNetwork\(\) is not this run's QNetwork\(\)"):
            check_train(compose_cfg("train", tiny("B") + [f"mode.stage1.init={run}"]))


def assert_loads_back_everywhere(compose_cfg, run, trained: nn.Module, cls: type) -> None:
    """``run``'s ``final.pt`` is ``trained`` (a ``cls``) for evaluate, deploy and the opponent
    pool: the same class and weights, the same Q-values and greedy action on fixed input."""
    x = fixed_input()
    want = trained(x)
    # evaluate: the policy source that `memrl.evaluate policy=checkpoint` instantiates
    ecfg = compose_cfg("evaluate", [f"policy.run={run}"])
    [cand] = instantiate(ecfg.policy).candidates()
    assert type(cand.actor.net) is cls and equal_weights(cand.actor.net, trained)
    assert torch.equal(cand.actor.policy.q_values(x), GreedyPolicy(trained).q_values(x))
    # deploy: deploy.policy=checkpoint
    dcfg = compose_cfg("deploy", ["deploy.policy=checkpoint", f"deploy.checkpoint={run}"])
    policy = make_policy(deploy_config(dcfg.deploy))
    assert type(policy.net) is cls and torch.equal(policy.net(x), want)
    assert policy.act(x[0].numpy()) == int(want[0].argmax())
    # the opponent pool, from the run's own final.pt
    index = torch.zeros(len(x), dtype=torch.long)
    pool = LearnedCarController([str(run / "checkpoints" / "final.pt")])
    assert torch.equal(pool.q_values(index, x), LearnedCarController([trained]).q_values(index, x))


def test_a_checkpoint_saved_before_the_network_key_resumes_as_table1(compose_cfg, tmp_path):
    cfg = compose_cfg("train", TINY)
    run = tmp_path / "run"
    train(cfg, run)
    where = ckpt.find(run)
    state = torch.load(where / "state.pt", weights_only=False)
    del state["config"]["network"]  # as written before the network group
    torch.save(state, where / "state.pt")
    ckpt.write_manifest(where)
    ckpt.load_state(where, cfg)  # the default network=table1 matches
    with pytest.raises(ckpt.CheckpointError, match="network._target_"):
        ckpt.load_state(where, compose_cfg("train", TINY + ["network=dueling"]))


def test_a_pool_of_one_architecture_gives_each_car_exactly_its_own_networks_q_values():
    """Cars of several networks of one architecture: each car's Q-values are those of its own
    network run alone, to the bit (one forward per network on its own cars)."""
    torch.manual_seed(0)
    nets = [QNetwork() for _ in range(3)]
    pool = LearnedCarController(nets)
    x, index = fixed_input(7), torch.tensor([2, 0, 1, 2, 0, 0, 1])
    got = pool.q_values(index, x)
    for i, net in enumerate(nets):
        rows = index == i
        assert torch.equal(got[rows], net(x[rows]))


def test_a_pool_of_several_architectures_gives_each_car_its_own_networks_q_values(tmp_path):
    torch.manual_seed(0)
    nets = [QNetwork(), build_qnet(DUELING), build_qnet({**TABLE1, "layernorm": True})]
    files = [str(save_qnet(tmp_path / f"a{i}" / "final.pt", n, {})) for i, n in enumerate(nets)]
    pool = LearnedCarController(files)
    x, index = fixed_input(6), torch.tensor([0, 1, 2, 2, 1, 0])
    got = pool.q_values(index, x)
    for i, net in enumerate(nets):
        rows = index == i
        assert torch.equal(got[rows], LearnedCarController([net]).q_values(index[rows] * 0, x[rows]))
