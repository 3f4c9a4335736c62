"""Does the learner see its crash coming: Q against the return by steps before a crash, the
action gaps and the TD error, each against a hand computation; the runners record the Q-values
acted on (both runners alike, the records unchanged); an evaluation writes the section into
``eval.json``, ``eval.md`` and the report."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from memrl.envs.lane_change import LaneChangeEnv
from memrl.envs.vehicles import IDLE
from memrl.evaluate import evaluate
from memrl.evaluation import crash_sight as cs
from memrl.evaluation.policies import GreedyActor
from memrl.evaluation.protocol import ProtocolConfig, protocol_env, scenario_seeds
from memrl.evaluation.runner import Job, run_jobs
from memrl.evaluation.sight_tables import TITLE, sight_lines
from memrl.modules.policy import FrameStack
from memrl.modules.qnet import QNetwork
from memrl.report import report
from tests.eval_helpers import fake_run

GAMMA = 0.5


def q_rows(taken: list[float], actions: list[int], others: float = -1.0) -> np.ndarray:
    """Q ``[T, 9]``: ``taken[t]`` at ``actions[t]``, ``others`` elsewhere."""
    q = np.full((len(taken), 9), others, dtype=np.float32)
    q[np.arange(len(taken)), actions] = taken
    return q


def hand_episodes() -> list[cs.EpisodeTrace]:
    """Two crashes (after 4 and 2 steps) and a survivor of a 6-step protocol, gamma 0.5."""
    return [
        cs.EpisodeTrace("non_goal", 0, q_rows([10, 8, 6, 4], [4, 4, 1, 7]), np.array([4, 4, 1, 7]),
                        np.array([1.0, 1.0, 1.0, -5.0]), crashed=True),
        cs.EpisodeTrace("non_goal", 1, q_rows([3, 2], [0, 0]), np.array([0, 0]), np.array([1.0, -5.0]),
                        crashed=True),
        cs.EpisodeTrace("non_goal", 2, q_rows([5, 5, 5, 5, 9, 9], [4] * 6), np.array([4] * 6),
                        np.full(6, 2.0), crashed=False),
    ]


def test_discounted_returns_by_hand():
    # G3 = -5, G2 = 1 + 0.5 * -5 = -1.5, G1 = 1 + 0.5 * -1.5 = 0.25, G0 = 1 + 0.5 * 0.25 = 1.125
    assert cs.discounted_returns(np.array([1.0, 1.0, 1.0, -5.0]), GAMMA).tolist() == [1.125, 0.25, -1.5, -5.0]
    assert cs.survivor_steps(300) == 200 and cs.survivor_steps(6) == 4 and cs.survivor_steps(25) == 17


def test_q_and_return_binned_by_steps_before_the_crash_by_hand():
    rows = {r["steps"]: r for r in cs.calibration(hand_episodes(), GAMMA, duration=6)}
    assert list(rows) == ["1", "2", "3-5", "6-10", "11-20", "21-40", "survivors"]
    # 1 step before: the crash steps, Q 4 and 2, G -5 and -5
    assert (rows["1"]["n"], rows["1"]["q"], rows["1"]["g"]) == (2, 3.0, -5.0)
    # 2 before: Q 6 (G -1.5) and 3 (G 1 + 0.5 * -5 = -1.5)
    assert (rows["2"]["n"], rows["2"]["q"], rows["2"]["g"]) == (2, 4.5, -1.5)
    # 3-5 before: the first episode's steps 1 and 2 (4 and 3 before): Q 10, 8; G 1.125, 0.25
    assert (rows["3-5"]["n"], rows["3-5"]["q"], rows["3-5"]["g"]) == (2, 9.0, 0.6875)
    assert rows["6-10"] == {"steps": "6-10", "n": 0, "q": None, "g": None}
    # survivors: its first 4 of 6 steps; G of +2 per step: 3.9375, 3.875, 3.75, 3.5
    assert (rows["survivors"]["n"], rows["survivors"]["q"]) == (4, 5.0)
    assert rows["survivors"]["g"] == pytest.approx((3.9375 + 3.875 + 3.75 + 3.5) / 4, abs=1e-4)
    assert "q_risk" not in rows["1"]


def test_risk_of_the_action_taken_is_binned_when_the_network_outputs_one():
    eps = hand_episodes()
    eps[0].risk = np.array([0.1, 0.2, 0.3, 0.9])  # per state
    eps[1].risk = np.zeros((2, 9))
    eps[1].risk[:, 0] = [0.5, 0.7]  # per action: the taken one (0) counts
    eps[2].risk = np.full(6, 0.05)
    rows = {r["steps"]: r for r in cs.calibration(eps, GAMMA, duration=6)}
    assert rows["1"]["q_risk"] == pytest.approx(0.8) and rows["2"]["q_risk"] == pytest.approx(0.4)
    assert rows["3-5"]["q_risk"] == pytest.approx(0.15) and rows["survivors"]["q_risk"] == pytest.approx(0.05)


def test_the_masks_share_counts_steps_whose_action_is_not_the_greedy_one_by_hand():
    eps = hand_episodes()
    eps[0].risk, eps[2].risk = np.zeros((4, 9)), np.zeros((6, 9))  # per action; eps[1]: no risk
    eps[0].q[0, 0] = eps[0].q[3, 2] = 20.0  # its steps 4 and 1 before the crash: argmax is not the action
    eps[2].q[1, 8] = 99.0  # the survivor's step 2 (of its 4 kept)
    rows = {r["steps"]: r for r in cs.calibration(eps, GAMMA, duration=6)}
    # 1 before: eps[0]'s last step (masked) and eps[1]'s (no risk: not counted)
    assert (rows["1"]["masked"], rows["2"]["masked"], rows["3-5"]["masked"]) == (1.0, 0.0, 0.5)
    assert rows["survivors"]["masked"] == 0.25 and rows["6-10"]["masked"] is None
    assert (rows["1"]["q"], rows["3-5"]["q"]) == (3.0, 9.0)  # Q of the action taken, as before
    for ep in eps:
        ep.risk = np.full(len(ep.actions), 0.1)  # per state: a risk, no mask
    assert all("masked" not in r and r["q_risk"] is not None
               for r in cs.calibration(eps, GAMMA, duration=6) if r["n"])
    sight = cs.summarize(hand_episodes()[:1], GAMMA, 6)
    assert "masked" not in sight["lanes"]["non_goal"]["calibration"][0]


def test_risk_calibration_against_the_crashes_that_followed_by_hand():
    eps = hand_episodes()
    eps[0].risk = np.array([0.01, 0.03, 0.3, 0.9])  # per state
    eps[1].risk = np.zeros((2, 9))
    eps[1].risk[:, 0] = [0.15, 0.6]  # per action: the taken one (0) counts
    eps[2].risk = np.array([0.0, 0.01, 0.04, 1.0, 0.9, 0.9])  # its last 2 steps are cut (6 - 6 // 3)
    # gamma_risk 0.5: horizon round(1 / 0.5) = 2 steps; realized 0.5^k, k steps from the action to the crash
    rows = {r["risk"]: r for r in cs.risk_calibration(eps, 0.5, duration=6)}
    assert list(rows) == ["0-0.02", "0.02-0.05", "0.05-0.1", "0.1-0.2", "0.2-0.5", "0.5-1"]
    # 0-0.02: episode 0 step 0 (k 3: 0.125, not within 2), survivor steps 0, 1 (0)
    assert rows["0-0.02"]["n"] == 3 and rows["0-0.02"]["predicted"] == pytest.approx(0.02 / 3, abs=1e-4)
    assert rows["0-0.02"]["realized"] == pytest.approx(0.125 / 3, abs=1e-4) and rows["0-0.02"]["within"] == 0
    # 0.02-0.05: episode 0 step 1 (k 2: 0.25, not within) and the survivor's step 2 (0)
    low = rows["0.02-0.05"]
    assert (low["n"], low["realized"], low["within"]) == (2, 0.125, 0)
    assert rows["0.05-0.1"] == {"risk": "0.05-0.1", "n": 0, "predicted": None, "realized": None,
                                "within": None}
    # 0.1-0.2: episode 1 step 0 (k 1: 0.5, within)
    assert (rows["0.1-0.2"]["n"], rows["0.1-0.2"]["realized"], rows["0.1-0.2"]["within"]) == (1, 0.5, 1)
    # 0.2-0.5: episode 0 step 2 (k 1: 0.5, within)
    assert (rows["0.2-0.5"]["n"], rows["0.2-0.5"]["realized"], rows["0.2-0.5"]["within"]) == (1, 0.5, 1)
    # 0.5-1 (1 included): episode 0 step 3 and episode 1 step 1 (k 0: 1, within), survivor step 3 (0)
    assert (rows["0.5-1"]["n"], rows["0.5-1"]["within"]) == (3, pytest.approx(2 / 3, abs=1e-4))
    assert rows["0.5-1"]["predicted"] == pytest.approx(2.5 / 3, abs=1e-4)
    assert rows["0.5-1"]["realized"] == pytest.approx(2 / 3, abs=1e-4)
    sight = cs.summarize(eps, GAMMA, 6, gamma_risk=0.5)
    assert sight["gamma_risk"] == 0.5
    assert sight["lanes"]["non_goal"]["risk_calibration"] == list(rows.values())
    no_risk = cs.summarize(hand_episodes(), GAMMA, 6, gamma_risk=0.5)
    assert "risk_calibration" not in no_risk["lanes"]["non_goal"]
    # pooled over two units: counts summed, means weighted by steps
    block = sight["lanes"]["non_goal"]
    pooled = cs.pool([block, block])["risk_calibration"]
    assert pooled[0]["n"] == 6 and pooled[0]["realized"] == rows["0-0.02"]["realized"]


def test_td_error_by_hand():
    first, _, survivor = hand_episodes()
    # next max Q: 8, 6, 4 (the taken ones; the others are -1); at the crash the target is -5
    # |10 - (1 + 4)|, |8 - (1 + 3)|, |6 - (1 + 2)|, |4 - (-5)|
    assert cs.td_errors(first.q, first.actions, first.rewards, True, GAMMA).tolist() == [5.0, 4.0, 3.0, 9.0]
    # the survivor's last step is left out (its next state was never acted on)
    err = cs.td_errors(survivor.q, survivor.actions, survivor.rewards, False, GAMMA)
    assert err.tolist() == [0.5, 0.5, 0.5, 1.5, 2.5]  # |5 - 4.5| x 3, |5 - 6.5|, |9 - 6.5|
    # the bootstrap takes the best next action, not the one taken
    q = q_rows([1.0, 0.0], [0, 0])
    q[1, 5] = 4.0
    assert cs.td_errors(q, np.array([0, 0]), np.array([0.0, 0.0]), True, GAMMA).tolist() == [1.0, 0.0]


def test_action_gap_percentiles_by_hand():
    q = np.array([[0, 1, 2, 3, 4, 5, 6, 7, 8],  # best 8 (faster, curvature +): second 7
                  [0, 0, 0, 5, 1, 2, 0, 3, 0],  # best 5 at index 3 (keep, curvature -): second 3
                  [9, 0, 0, 0, 0, 0, 0, 0, 0]], dtype=np.float32)  # best 9 (slower, curvature -)
    g = cs.action_gaps(q)
    assert g["best_second"].tolist() == [1, 2, 9]
    # over the speeds at the greedy curvature: {2, 5, 8}, {0, 5, 0}, {9, 0, 0}
    assert g["speed_gap"].tolist() == [6, 5, 9]
    assert g["curvature_gap"].tolist() == [2, 4, 9]  # {6,7,8}, {5,1,2}, {9,0,0}
    assert g["speed"].tolist() == [2, 1, 0]
    # numpy's linear percentiles of [1, 2, 9]: 1.2, 2, 7.6
    assert cs.percentiles(g["best_second"]) == [1.2, 2.0, 7.6]
    trace = cs.EpisodeTrace("random", 0, q, np.argmax(q, 1), np.zeros(3), crashed=True)
    out = cs.gaps([trace], GAMMA)
    assert out["states"] == 3 and out["greedy_speed"] == {"slower": 1, "keep": 1, "faster": 1}
    assert out["speed_gap"] == [5.2, 6.0, 8.4] and out["curvature_gap"] == [2.4, 4.0, 8.0]
    # TD: |8 - 0.5 * 5|, |5 - 0.5 * 9|, |9 - 0|
    assert out["td_n"] == 3 and out["td"] == pytest.approx((5.5 + 0.5 + 9) / 3, abs=1e-4)


def test_pooling_weights_by_steps_and_averages_percentiles():
    a = cs.summarize(hand_episodes(), GAMMA, 6)["lanes"]["non_goal"]
    b = cs.summarize(hand_episodes()[:1], GAMMA, 6)["lanes"]["non_goal"]
    p = cs.pool([a, b])
    rows = {r["steps"]: r for r in p["calibration"]}
    # bin 1: a's two steps (mean 3) and b's one (4): (2 * 3 + 4) / 3
    assert rows["1"]["n"] == 3 and rows["1"]["q"] == pytest.approx(10 / 3, abs=1e-4)
    assert (p["units"], p["episodes"], p["crashes"], p["crashes_per_unit"]) == (2, 4, 3, [2, 1])
    assert p["gaps"]["states"] == 12 + 4 and p["gaps"]["td_n"] == a["gaps"]["td_n"] + 4
    assert p["gaps"]["best_second"] == pytest.approx(
        [(x + y) / 2 for x, y in zip(a["gaps"]["best_second"], b["gaps"]["best_second"], strict=True)])


# --------------------------------------------------------------------------- the runners
def qnet(seed: int, idle_bias: float) -> QNetwork:
    torch.manual_seed(seed)
    net = QNetwork()
    with torch.no_grad():
        net.head[-1].weight.mul_(30.0)  # spread Q-values: no near-ties for the batch to flip
        net.head[-1].bias[IDLE] += idle_bias
    return net


def test_both_runners_record_the_q_values_they_acted_on():
    p = ProtocolConfig(episodes=4, duration=40, vehicles_count=[3, 5])
    seeds = list(enumerate(scenario_seeds(p.seed, 4)))
    jobs = [Job(protocol_env({}, p, lane), lane, seeds) for lane in p.initial_lanes]
    actor = GreedyActor(qnet(0, 0.0), gamma=0.95)
    plain = run_jobs(actor, jobs, engine=True)
    engine = run_jobs(actor, jobs, engine=True, record=True)
    gym = run_jobs(actor, jobs, engine=False, record=True, batch=3)
    assert engine.records == plain.records and plain.traces == []  # recording changes no episode
    assert len(engine.traces) == len(gym.traces) == 8
    assert any(r.collided for r in engine.records) and any(not r.collided for r in engine.records)
    for rec, a, b in zip(engine.records, engine.traces, gym.traces, strict=True):
        assert (a.initial_lane, a.episode, a.crashed) == (rec.initial_lane, rec.episode, rec.collided)
        assert len(a.q) == len(b.q) == rec.steps and a.q.shape[1] == 9
        assert a.actions.tolist() == b.actions.tolist() == a.q.argmax(1).tolist()
        assert float(a.rewards.sum()) == pytest.approx(rec.episode_return, abs=1e-4)
        np.testing.assert_allclose(a.q, b.q, rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(a.rewards, b.rewards)
    # the Q-values are the network's on the episode's own frames (its first state, by hand)
    first = engine.traces[0]
    env = LaneChangeEnv(config=jobs[0].env)
    obs, _ = env.reset(seed=seeds[0][1])
    stack = FrameStack(4, env.cfg.frame_stride)
    stack.reset(obs)
    with torch.no_grad():
        q0 = qnet(0, 0.0)(torch.from_numpy(stack.frames)[None])[0].numpy()
    np.testing.assert_allclose(first.q[0], q0, rtol=1e-4, atol=1e-3)


class RiskNet(QNetwork):
    """A Q-network that declares a crash-risk output beside its Q-values."""

    def outputs(self, pixels: torch.Tensor) -> dict[str, torch.Tensor]:
        q = self(pixels)
        return {"q": q, "risk": torch.sigmoid(q / 10)}


def test_a_risk_output_is_recorded_and_reported():
    torch.manual_seed(0)
    p = ProtocolConfig(episodes=2, duration=20)
    jobs = [Job(protocol_env({}, p, "non_goal"), "non_goal", list(enumerate(scenario_seeds(0, 2))))]
    res = run_jobs(GreedyActor(RiskNet(), gamma=0.9), jobs, record=True)
    tr = res.traces[0]
    assert tr.risk is not None and tr.risk.shape == tr.q.shape
    np.testing.assert_allclose(tr.risk, 1 / (1 + np.exp(-tr.q / 10)), rtol=1e-5)
    sight = cs.summarize(res.traces, 0.9, 20)
    assert all("q_risk" in row for row in sight["lanes"]["non_goal"]["calibration"])

    class Result:  # what sight_lines reads of an evaluation
        crash_sight, meta = sight, {"kind": "checkpoint"}

    text = "\n".join(sight_lines([("B", [Result()])]))  # type: ignore[list-item]
    assert "**q_risk, by steps before a crash.**" in text
    assert "**The mask's share, by steps before a crash.**" in text  # a risk per action
    assert "**The crash-risk head's calibration.**" not in text  # no gamma_risk: no calibration
    Result.crash_sight = cs.summarize(res.traces, 0.9, 20, gamma_risk=0.8)
    text = "\n".join(sight_lines([("B", [Result()])]))  # type: ignore[list-item]
    assert "**The crash-risk head's calibration.**" in text and "| risk 0.5-1 |" in text


# --------------------------------------------------------------------------- end to end
def test_an_evaluation_writes_the_section_and_the_report_pools_it(tmp_path, compose_cfg):
    run = fake_run(tmp_path / "sweep", compose_cfg, seed=0)
    small = ["protocol.episodes=3", "protocol.duration=25", "workers=1", "batch=2", "progress=false"]
    [result] = evaluate(compose_cfg("evaluate", [f"policy.run={run}", *small]), out_dir=tmp_path / "unused")
    doc = json.loads((run / "eval" / "eval.json").read_text())
    sight = doc["crash_sight"]
    assert sight["gamma"] == 0.95 and sight["duration"] == 25 and sight["survivor_steps"] == 17
    assert list(sight["lanes"]) == ["random", "non_goal"]
    records = result.records()
    for lane, block in sight["lanes"].items():
        mine = [r for r in records if r.initial_lane == lane]
        assert block["episodes"] == 3 and block["crashes"] == sum(r.collided for r in mine)
        rows = {r["steps"]: r for r in block["calibration"]}
        assert rows["1"]["n"] == block["crashes"]  # one step 1-before per crash
        assert rows["survivors"]["n"] == 17 * sum(not r.collided for r in mine)
        assert block["gaps"]["states"] == sum(r.steps for r in mine)
        assert block["gaps"]["td_n"] == sum(r.steps - (not r.collided) for r in mine)
    md = (run / "eval" / "eval.md").read_text()
    assert TITLE in md and "| Default | non-goal | 3 |" in md and "survivors (steps 1\u201317)" in md
    files = report(compose_cfg("report", [f"runs=[{tmp_path / 'sweep'}]", "evaluate_missing=false",
                                          "rollouts.rows=[]", "progress=false", "n_resamples=200",
                                          "fig5=false"]), out_dir=tmp_path / "out")
    table = files.table_md.read_text()
    assert TITLE in table and "| Default | random | 3 |" in table and "TD error (steps)" in table


def test_policies_without_q_values_say_so(tmp_path, compose_cfg):
    cfg = compose_cfg("evaluate", ["policy=scripted", "protocol.episodes=1", "protocol.duration=5",
                                   "workers=1", "progress=false"])
    [result] = evaluate(cfg, out_dir=tmp_path)
    assert result.crash_sight is None
    assert "crash_sight" not in json.loads((tmp_path / "eval.json").read_text())
    assert "No evaluation here recorded its Q-values" in (tmp_path / "eval.md").read_text()
