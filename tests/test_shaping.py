"""Potential-based shaping by collision risk (env.shaping, memrl.envs.risk): the risk against hand
computations of each kind of threat, one formula for numpy and torch, the shaped reward's
telescoping sum over an episode, both engines alike, and the config checks."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from memrl.dqn.config import check_train_config
from memrl.envs.config import EnvConfigError
from memrl.envs.lane_change import LaneChangeEnv
from memrl.envs.risk import risk, shaping_reward
from memrl.errors import ConfigError
from tests.batched_helpers import compare, random_actions
from tests.helpers import TINY

L, W, LANE, T = 5.0, 2.0, 4.0, 3.0


def one(rows: list[list[float]], present: list[bool] | None = None) -> float:
    state = np.array(rows, dtype=np.float64)
    mask = np.ones(len(rows), dtype=bool) if present is None else np.array(present)
    return float(risk(state, mask, LANE, 2, L, W, T))


def test_a_car_ahead_closing_at_2_m_s_with_a_5_m_gap_is_a_2_5_s_threat():
    # centres 10 m apart: bumper gap 10 - 5 = 5 m, closing 8 - 6 = 2 m/s, ttc 2.5 s
    assert one([[0, 0, 0, 8, 0], [10, 0, 0, 6, 0]]) == pytest.approx(1 - 2.5 / 3, abs=1e-15)


def test_a_faster_car_behind_is_a_threat_and_a_slower_one_is_not():
    # 11 m behind at 9 m/s against 6: gap 6 m, closing 3 m/s, ttc 2 s
    assert one([[0, 0, 0, 6, 0], [-11, 0, 0, 9, 0]]) == pytest.approx(1 - 2 / 3, abs=1e-15)
    assert one([[0, 0, 0, 6, 0], [-11, 0, 0, 5, 0]]) == 0.0


def test_a_car_in_the_other_lane_is_no_threat_along_the_road():
    # 4 m across (one lane): no overlap across the road, so its closing speed does not count
    assert one([[0, 0, 0, 8, 0], [10, 4, 0, 2, 0]]) == 0.0


def test_a_car_beside_is_a_threat_when_the_agent_drifts_toward_it():
    # beside (|dx| 1 < 5), 3.5 m apart across: gap 1.5 m; heading 0.1 at 8 m/s, 0.79867 m/s
    # toward it (y grows toward lane 1): ttc 1.5 / (8 sin 0.1); the edge is farther in time
    h = 0.1
    vy = 8 * np.sin(h)
    got = one([[0, 0.5, h, 8, 0], [1, 4.0, 0, 8, 0]])
    edge_gap = 1.5 * LANE - (0.5 + 0.5 * (L * np.sin(h) + W * np.cos(h)))
    assert 1.5 / vy < edge_gap / vy
    assert got == pytest.approx(1 - (1.5 / vy) / 3, abs=1e-12)


def test_the_road_edge_is_a_threat_when_the_agent_steers_toward_it():
    # lane 0 centre (y 0), heading -0.05 rad at 8 m/s: toward the edge at y = -2; the body's
    # lowest corner is at -0.5 (L sin 0.05 + W cos 0.05)
    h = -0.05
    half = 0.5 * (L * np.sin(-h) + W * np.cos(h))
    ttc = (2.0 - half) / (8 * np.sin(-h))
    assert ttc < T
    assert one([[0, 0, h, 8, 0]]) == pytest.approx(1 - ttc / 3, abs=1e-12)
    assert one([[0, 0, -h, 8, 0]]) == 0.0  # toward the other edge, 6 m away: beyond 3 s


def test_absent_slots_and_far_cars_carry_no_risk():
    rows = [[0, 0, 0, 8, 0], [6, 0, 0, 0, 0]]  # a stopped car 1 m ahead: ttc 1/8 s
    assert one(rows) == pytest.approx(1 - (1 / 8) / 3, abs=1e-15)
    assert one(rows, [True, False]) == 0.0
    assert one([[0, 0, 0, 8, 0], [100, 0, 0, 0, 0]]) == 0.0  # 95 m at 8 m/s: beyond 3 s


def test_numpy_and_torch_compute_the_same_risk_on_random_scenes():
    rng = np.random.default_rng(0)
    n, c = 256, 6
    state = np.zeros((n, c, 5))
    state[..., 0] = rng.uniform(-30, 30, (n, c))
    state[..., 1] = rng.uniform(-1.5, 5.5, (n, c))
    state[..., 2] = rng.uniform(-0.2, 0.2, (n, c))
    state[..., 3] = rng.uniform(0, 12, (n, c))
    state[:, 0, :2] = 0.0
    present = rng.random((n, c)) < 0.7
    a = risk(state, present, LANE, 2, L, W, T)
    b = risk(torch.from_numpy(state), torch.from_numpy(present), LANE, 2, L, W, T).numpy()
    assert a.shape == (n,) and ((a > 0) & (a < 1)).sum() > 50  # a spread of real threats
    np.testing.assert_allclose(b, a, rtol=0, atol=1e-12)  # float64; sin/cos may differ in an ulp


def test_the_shaping_reward_is_zero_after_a_crash_and_discounted_otherwise():
    before, after = np.array([0.4, 0.4]), np.array([0.9, 0.9])
    got = shaping_reward(before, after, np.array([False, True]), 2.0, 0.95)
    np.testing.assert_allclose(got, [2.0 * (0.4 - 0.95 * 0.9), 2.0 * 0.4], rtol=1e-15)


@pytest.mark.parametrize("seed", [3, 11])
def test_shaped_rewards_telescope_over_an_episode(seed):
    """sum_t gamma^t (r_shaped - r_plain) = gamma^T Phi(s_T) - Phi(s_0), Phi = -w risk, and
    Phi(s_T) = 0 after a crash: the return changes by the start state's potential alone."""
    w, gamma = 2.0, 0.95
    base = {"initial_lane": "non_goal", "vehicles_count": 5}
    plain = LaneChangeEnv(config=base)
    shaped = LaneChangeEnv(config={**base, "shaping": {"weight": w, "gamma": gamma}})
    plain.reset(seed=seed)
    shaped.reset(seed=seed)
    risk0 = shaped.state_risk()
    rng = np.random.default_rng(seed)
    total, t, end = 0.0, 0, False
    saw_risk = False
    while not end:
        a = int(rng.integers(9)) if rng.random() < 0.3 else 1  # mostly faster: closing in
        _, r0, term, trunc, _ = plain.step(a)
        _, r1, term1, trunc1, _ = shaped.step(a)
        assert (term, trunc) == (term1, trunc1)
        total += gamma ** t * (r1 - r0)
        saw_risk |= shaped.state_risk() > 0
        t += 1
        end = term or trunc
    last = 0.0 if term else shaped.state_risk()
    assert saw_risk
    assert total == pytest.approx(-w * (gamma ** t * last) + w * risk0, abs=1e-9)


def test_both_engines_give_the_same_shaped_rewards():
    config = {"initial_lane": "non_goal", "vehicles_count": [0, 5],
              "shaping": {"weight": 2.0, "horizon": 3.0, "gamma": 0.95}}
    tally = compare(config, list(range(12)), 150, random_actions(1.0))
    assert tally.steps == 12 * 150 and tally.collisions > 0


def test_bad_shaping_values_are_refused_in_one_line(compose_cfg):
    with pytest.raises(EnvConfigError, match="shaping.weight"):
        LaneChangeEnv(config={"shaping": {"weight": -1.0}})
    with pytest.raises(EnvConfigError, match="shaping.horizon"):
        LaneChangeEnv(config={"shaping": {"horizon": 0.0}})
    cfg = compose_cfg("train", TINY + ["env.shaping.weight=1.0", "agent.gamma=0.99"])
    with pytest.raises(ConfigError, match="env.shaping.gamma.*agent.gamma"):
        check_train_config(cfg)
    check_train_config(compose_cfg("train", TINY + ["env.shaping.weight=1.0", "agent.gamma=0.99",
                                                    "env.shaping.gamma=0.99"]))


def test_a_short_run_with_shaping_trains_and_resumes(compose_cfg, tmp_path):
    from memrl.train import train

    extra = ["env.shaping.weight=1.0", "total_episodes=null", "total_frames=300",
             "agent.warmup_frames=100", "buffer.capacity=1000"]
    summary = train(compose_cfg("train", TINY + extra), tmp_path / "run")
    assert summary.frames >= 300 and summary.updates > 0
    again = train(compose_cfg("train", TINY + extra[:-3] + ["total_frames=400", "agent.warmup_frames=100",
                                                            "buffer.capacity=1000",
                                                            f"resume={tmp_path / 'run'}"]))
    assert again.frames >= 400
    with pytest.raises(Exception, match="shaping"):  # a resume must keep the shaping it trained with
        train(compose_cfg("train", TINY + ["total_episodes=null", "total_frames=500",
                                           "agent.warmup_frames=100", "buffer.capacity=1000",
                                           f"resume={tmp_path / 'run'}"]))
