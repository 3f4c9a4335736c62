"""The stage-1 probe (``python -m memrl.tools.stage1_probe``): dead units counted exactly, and
a run config's first stage-1 updates reported from the same initial weights the trainer has."""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf
from torch import nn

from memrl.tools.stage1_probe import dead_units, fingerprint, main
from tests.helpers import make_demos, save_pool, tiny


def test_dead_units_counts_the_units_no_state_activates():
    """Layer 1: unit 0 is x0 - x1, unit 1 is -1 (never on), unit 2 is x0; layer 2 reads the
    first layer's units: unit 0 = h0 (on for state (2, 0)), unit 1 = -h2 (never on)."""
    net = nn.Sequential(nn.Linear(2, 3), nn.ReLU(), nn.Linear(3, 2), nn.ReLU())
    with torch.no_grad():
        net[0].weight.copy_(torch.tensor([[1.0, -1.0], [0.0, 0.0], [1.0, 0.0]]))
        net[0].bias.copy_(torch.tensor([0.0, -1.0, 0.0]))
        net[2].weight.copy_(torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]))
        net[2].bias.zero_()
    states = torch.tensor([[2.0, 0.0], [0.0, 3.0]])
    assert dead_units(net, states) == [1, 1]
    assert dead_units(net, states[1:]) == [3, 2]  # (0, 3) alone: x0 - x1 < 0, x0 = 0 (not > 0)
    # conv maps: a channel counts as alive when any position of any state is positive
    conv = nn.Sequential(nn.Conv2d(1, 2, 1), nn.ReLU())
    with torch.no_grad():
        conv[0].weight.copy_(torch.tensor([1.0, -1.0]).reshape(2, 1, 1, 1))
        conv[0].bias.zero_()
    image = torch.zeros(1, 1, 3, 3)
    image[0, 0, 1, 1] = 1.0
    assert dead_units(conv, image) == [1]


def test_the_probe_reports_the_trainers_first_stage1_updates(compose_cfg, tmp_path, capsys):
    from memrl.data.demos import save_demos
    from memrl.dqn.loop import Trainer
    from memrl.train import prior_knowledge

    demos = save_demos(make_demos(120), tmp_path / "demos",
                       {"env_config": {"duration": 30, "vehicles_count": 0}})
    # path_time 0: the frames make_demos draws (the env defaults), which the dataset check compares
    cfg = compose_cfg("train", tiny("B") + [f"mode.demos_path={demos}", "env.bev.path_time=0"])
    run = tmp_path / "run"
    run.mkdir()
    cfg.paths.output_dir = str(run)  # as a run's config.yaml has it
    OmegaConf.save(cfg, run / "config.yaml", resolve=True)
    expected = fingerprint(Trainer(cfg, tmp_path / "reference", demos=prior_knowledge(cfg)).learner.qnet)
    pool = save_pool(tmp_path / "pool", seeds=(1,))
    for extra in ([], ["env.opponent.type=mixed", f"env.opponent.pool=[{pool[0]}]"]):
        assert main([str(run), "updates=6", "every=3", *extra]) == 0
        lines = capsys.readouterr().out.strip().splitlines()
        assert [int(row.split()[1]) for row in lines] == [0, 3, 6]
        assert lines[0].endswith(f"init {expected}")  # the pool leaves the initial weights alone
        assert all("greedy actions" in row and "Q(s, a_demo) - return " in row for row in lines)
    default = compose_cfg("train", tiny())
    default.paths.output_dir = str(tmp_path / "default")
    OmegaConf.save(default, tmp_path / "default.yaml", resolve=True)
    for argv, message in (([str(run), "env.opponent.tpye=constant"], "override: Key 'tpye' is not in struct"),
                          ([str(tmp_path / "default.yaml")], "mode default starts online")):
        assert main([*argv, "updates=1"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], err


def test_the_probe_reads_a_trained_network_on_seeded_demo_states(tmp_path, capsys):
    """weights=final: the counts of dead units, the dead conv channels and the greedy actions
    on the 256 demo states that a generator seeded 0 picks, computed here directly."""
    from memrl.checkpoint import save_qnet
    from memrl.data.demos import load_demos, save_demos
    from memrl.modules.qnet import QNetwork
    from memrl.tools.stage1_probe import calibration, calibration_line, dead_indices

    # 150-step episodes: the steps 100 or more before their time limit have a known return
    demos = save_demos(make_demos(300, duration=150), tmp_path / "demos",
                       {"env_config": {"duration": 150, "vehicles_count": 0}})
    torch.manual_seed(3)
    net = QNetwork()
    with torch.no_grad():
        net.features[3].bias[:5] = -1e4  # conv 2: channels 0-4 never active
    run = tmp_path / "run"
    save_qnet(run / "checkpoints" / "final.pt", net, {})
    OmegaConf.save(OmegaConf.create({"env": {"duration": 150, "vehicles_count": 0, "bev": {"path_time": 0}},
                                     "mode": {"name": "default"}, "agent": {"gamma": 0.95}}),
                   run / "config.yaml")
    td = load_demos(demos)
    pick = torch.randperm(td.shape[0], generator=torch.Generator().manual_seed(0))[:256]
    pixels = td["pixels"][pick]
    dead = dead_indices(net.eval(), pixels)
    with torch.no_grad():
        greedy = int(net(pixels).argmax(-1).unique().numel())
    assert dead[1][0] and set(range(5)) <= set(dead[1][1])  # the constructed dead channels
    assert main([str(run), "weights=final", f"demos={demos}"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    head = (f"weights final  dead per ReLU {[len(u) for _, u in dead]}  "
            f"dead channels of the conv layers {[u for c, u in dead if c]}  ")
    assert len(out) == 2 and out[0].startswith(head)
    assert out[0].endswith(f"greedy actions {greedy}")
    # the calibration over every demo step whose return is known (tests/test_mc_returns.py)
    assert out[1] == calibration_line(calibration(net, td, 0.95))
    assert out[1].startswith("calibration on ")
    assert main([str(run), "weights=final"]) == 2  # a Default run: no prior knowledge of its own
    assert "give demos=" in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    ([], "usage"), (["updates=3"], "usage"),
    (["RUN", "updates=0"], "updates must be a positive integer"),
    (["RUN", "weights=best"], "weights must be final or stage1"),
    (["NOWHERE"], "no run config"),
])
def test_bad_probe_arguments_give_one_line(tmp_path, capsys, argv, message):
    argv = [str(tmp_path) if a == "RUN" else str(tmp_path / a) if a == "NOWHERE" else a for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
