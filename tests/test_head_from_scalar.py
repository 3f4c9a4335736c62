"""A categorical stage 2 (C51, HL-Gauss) from a scalar stage 1: the converted output layer puts a
Gaussian around each of the scalar network's Q-values (against a float64 hand computation), the
converted network keeps its Q-values, and ``mode.stage1.init`` takes a Table I stage 1 for
``network=hlgauss``."""

from __future__ import annotations

import pytest
import torch

from memrl.modules.qnet import build_qnet
from tests.test_network import fixed_input

BOUNDS = {"v_min": -65.0, "v_max": 40.0}  # Table II's return bounds at gamma 0.95
HEADS = {"c51": {"_target_": "memrl.modules.categorical.CategoricalQNetwork", **BOUNDS},
         "hlgauss": {"_target_": "memrl.modules.hlgauss.HLGaussQNetwork", **BOUNDS}}


def scalar_net() -> torch.nn.Module:
    """Table I with its Q-values spread over [-5, 35] on the fixed inputs (as a trained one's)."""
    torch.manual_seed(0)
    net = build_qnet()
    with torch.no_grad():
        q = net(fixed_input())
        scale = 40.0 / float(q.max() - q.min())  # min -> -5, max -> 35
        net.head[-1].weight.mul_(scale)
        net.head[-1].bias.mul_(scale).add_(-5.0 - float(q.min()) * scale)
    return net


def converted(kind: str, scalar: torch.nn.Module) -> torch.nn.Module:
    net = build_qnet(HEADS[kind])
    state = scalar.state_dict()
    last = f"head.{len(net.head) - 1}"
    w, b = net.head_from_scalar(state[f"{last}.weight"], state[f"{last}.bias"])
    net.load_state_dict({**state, f"{last}.weight": w, f"{last}.bias": b})
    return net


@pytest.mark.parametrize("kind", ["c51", "hlgauss"])
def test_the_converted_head_is_a_gaussian_around_each_q_value(kind):
    scalar = scalar_net()
    net = converted(kind, scalar)
    x = fixed_input()
    with torch.no_grad():
        q = scalar(x).double()  # [B, A]
        logits = net.outputs(x)["logits"].double()
    z, s = net.support_values().double(), net.conversion_width()
    want = torch.softmax(-(z - q[..., None]) ** 2 / (2 * s * s), -1)  # the hand computation
    got = torch.softmax(logits, -1)
    # float32 logits of up to |z| |Q| / s^2 (about 1,000 here): their rounding moves the
    # probabilities by a few 1e-4 at most
    assert float((got - want).abs().max()) < 2e-3
    assert float(q.min()) > -5.01 and float(q.max()) < 35.01  # 3 s and more inside the support


@pytest.mark.parametrize("kind", ["c51", "hlgauss"])
def test_the_converted_network_keeps_the_q_values_and_the_greedy_actions(kind):
    scalar = scalar_net()
    net = converted(kind, scalar)
    x = fixed_input()
    with torch.no_grad():
        q, q_cat = scalar(x), net(x)
    # the mean of a Gaussian sampled on a grid of spacing <= s / 0.75, centred 3 s or more
    # inside the grid's ends, is its centre to about 2e-3 (the grid's ripple, the tail the ends
    # cut; the hand computation above has the same); the float32 logits move the
    # probabilities by ~1e-5
    err = float((q_cat - q).abs().max())
    assert err < 5e-3
    top2 = q.topk(2, -1).values
    clear = (top2[:, 0] - top2[:, 1]) > 2 * err
    assert bool(clear.any())
    assert torch.equal(q_cat.argmax(-1)[clear], q.argmax(-1)[clear])


def test_stage_2_with_hl_gauss_starts_from_a_scalar_stage_1(compose_cfg, tmp_path, demos):
    from omegaconf import open_dict

    from memrl.checkpoint import load_weights
    from memrl.dqn.loop import Trainer
    from memrl.schemas import check_train
    from memrl.train import train
    from tests.helpers import tiny

    plain = compose_cfg("train", tiny("B"))
    train(plain, tmp_path / "plain", demos=demos)
    # float32 convs (auto is bfloat16 on CPUs with native bf16), as the stage 1 read back below
    overrides = [*tiny("B"), "network=hlgauss", f"mode.stage1.init={tmp_path / 'plain'}",
                 "agent.precision=float32"]
    cfg = compose_cfg("train", overrides)
    check_train(cfg)  # the scalar twin of the head: accepted
    trainer = Trainer(cfg, tmp_path / "hl", demos)
    trainer.run_offline()  # takes the shared stage 1, its output layer converted
    assert trainer.counters.stage == "B2"
    from memrl.checkpoint import load_stage1_qnet

    stage1 = load_stage1_qnet(tmp_path / "plain" / "checkpoints" / "stage1.pt")
    x = fixed_input()
    with torch.no_grad():
        q1, q2 = stage1(x), trainer.learner.qnet(x)
    assert float((q2 - q1).abs().max()) < 5e-3  # as the test above
    # the target network too (synced at the switch), and the run's own stage1.pt is the converted one
    now = trainer.learner.loss_module.state_dict()
    online = {k: v for k, v in now.items() if k.startswith("value_network")}
    assert all(torch.equal(v, online[k.removeprefix("target_")]) for k, v in now.items()
               if k.startswith("target_value_network"))
    saved = load_weights(tmp_path / "hl" / "checkpoints" / "stage1.pt", "stage-1 weights")
    assert saved["network"]["_target_"].endswith("HLGaussQNetwork")
    # a scalar stage 1 of another trunk is refused, naming it
    with open_dict(cfg):
        cfg.network.hidden = 128
    with pytest.raises(ValueError, match=r"config 'mode.stage1.init': .*its network QNetwork\(\) is not "
                                         r"this run's HLGaussQNetwork\(.*\) nor its scalar twin "
                                         r"QNetwork\(hidden=128\)"):
        check_train(cfg)
