"""The evaluation protocol: scores, fixed scenes, observations equal to the TorchRL pipeline's,
batched and parallel runs equal to sequential ones, the entry point and its policies."""

from __future__ import annotations

import csv
import json
import pickle
import random
from concurrent.futures import Future

import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from memrl.checkpoint import GreedyQPolicy, load_qnet
from memrl.data.recording import record_episodes
from memrl.dqn.collector import episode_seed
from memrl.envs.lane_change import LaneChangeEnv
from memrl.envs.torchrl_env import make_env, unwrap
from memrl.envs.vehicles import N_ACTIONS, action_index
from memrl.evaluate import evaluate
from memrl.evaluation import runner
from memrl.evaluation.periodic import PERIODIC_CSV, PeriodicEvaluation, periodic_eval
from memrl.evaluation.policies import DriverActor, GreedyActor, HumanSource
from memrl.evaluation.protocol import (
    ProtocolConfig,
    ProtocolError,
    check_protocol,
    protocol_env,
    scenario_seeds,
    score,
    scores_by_lane,
)
from memrl.evaluation.runner import Job, run_job, run_jobs
from memrl.modules.human import KeyboardDriver
from memrl.modules.policy import DrivingPolicy, PolicyModule, RandomPolicy
from memrl.modules.qnet import QNetwork
from memrl.modules.scripted import ScriptedDriver
from tests.eval_helpers import fake_run, records

SMALL = ["protocol.episodes=3", "protocol.duration=25", "workers=1", "batch=2", "progress=false"]


# ----------------------------------------------------------------------------- scores
def test_scores_from_hand_built_records():
    recs = records(survived=[True, True, False, True, False], goal=[True, False, True, False, False])
    s = score(recs)
    assert (s.episodes, s.survival, s.goal) == (5, 3, 2)
    assert s.survival_score == pytest.approx(60.0) and s.goal_score == pytest.approx(40.0)
    assert s.mean_steps == pytest.approx((300 * 3 + 123 * 2) / 5)
    # goal counts a target lane reached before a later crash; survival needs all the steps
    assert recs[2].goal and not recs[2].survived
    short = records([True], [False])[0]
    short.steps = 299  # ended early without a collision (cannot happen in the env): not a survivor
    assert not short.survived
    both = scores_by_lane(records([True] * 4, [True] * 4, "non_goal")
                          + records([False, True], [False, False], "random"))
    assert list(both) == ["random", "non_goal"]
    assert both["random"].survival_score == 50.0 and both["non_goal"].goal_score == 100.0


def test_scenario_seeds_are_fixed_and_apart_from_training_seeds():
    seeds = scenario_seeds(0, 100)
    assert seeds == scenario_seeds(0, 100) and len(set(seeds)) == 100
    assert scenario_seeds(0, 5) == seeds[:5]  # episode i's scene does not depend on the count
    assert not set(seeds) & set(scenario_seeds(1, 100))
    assert not set(seeds) & set(scenario_seeds(0, 100, domain="periodic"))
    assert not set(seeds) & {episode_seed(0, i) for i in range(1000)}


def test_protocol_is_checked_naming_the_key():
    with pytest.raises(ProtocolError, match="initial_lanes"):
        check_protocol({"initial_lanes": ["left"]})
    with pytest.raises(ProtocolError, match="vehicles_count"):
        check_protocol({"vehicles_count": [3, 1]})
    env = protocol_env({"lanes_count": 3, "opponent": {"type": "learned", "pool": ["x"]}},
                       ProtocolConfig(), "non_goal")
    assert env["lanes_count"] == 3 and env["opponent"] == "constant"
    assert env["vehicles_count"] == [0, 5] and env["initial_lane"] == "non_goal"


def test_same_seeds_give_the_same_scenes():
    protocol = ProtocolConfig(episodes=4, duration=20)
    for lane in ("random", "non_goal"):
        cfg = protocol_env({}, protocol, lane)
        a, b = LaneChangeEnv(config=cfg), LaneChangeEnv(config=cfg)
        for seed in scenario_seeds(0, 4):
            obs_a, _ = a.reset(seed=seed)
            b.reset(seed=12345)  # another scene in between changes nothing
            obs_b, _ = b.reset(seed=seed)
            assert np.array_equal(obs_a, obs_b) and a.target_lane == b.target_lane
            assert [tuple(c.position) + (c.speed,) for c in a.road.vehicles] == \
                   [tuple(c.position) + (c.speed,) for c in b.road.vehicles]
            if lane == "non_goal":
                assert a.current_lane() != a.target_lane
    # two different policies meet the same scenes: same seeds, lanes and car counts
    jobs = [Job(protocol_env({}, protocol, "random"), "random", list(enumerate(scenario_seeds(0, 4))))]
    r1 = run_jobs(DriverActor(ScriptedDriver), jobs).records
    r2 = run_jobs(DriverActor(RandomPolicy, seeded=True), jobs).records
    key = [(r.seed, r.target_lane, r.start_lane, r.vehicles) for r in r1]
    assert key == [(r.seed, r.target_lane, r.start_lane, r.vehicles) for r in r2]
    assert len({r.vehicles for r in r1}) > 1 or len(r1) < 3  # 0-5 cars drawn per episode


# --------------------------------------------------------------- observations and speed paths
class Scripted(DrivingPolicy):
    """Replays a fixed action sequence and keeps the pixels it was shown."""

    def __init__(self) -> None:
        self.seen: list[np.ndarray] = []

    def act(self, env, pixels) -> int:
        self.seen.append(np.array(pixels))
        return [action_index(1, 1), action_index(0, -1), action_index(-1, 0)][len(self.seen) % 3]


def test_runner_sees_exactly_the_torchrl_pipeline_observations():
    cfg = protocol_env({}, ProtocolConfig(duration=40), "non_goal")
    seeds = scenario_seeds(0, 3)
    for seed in seeds:
        gym_policy, trl_policy = Scripted(), Scripted()
        rec = run_job(DriverActor(lambda p=gym_policy: p), Job(cfg, "non_goal", [(0, seed)])).records[0]
        env = make_env(cfg)
        td = env.reset(seed=seed)
        rollout = env.rollout(40, PolicyModule(trl_policy, unwrap(env)), auto_reset=False, tensordict=td,
                              break_when_any_done=True)
        assert len(gym_policy.seen) == len(trl_policy.seen) == rollout.shape[0] == rec.steps
        for g, t in zip(gym_policy.seen, trl_policy.seen, strict=True):
            assert g.shape == (4, 84, 84) and np.array_equal(g, t)
        assert rec.episode_return == pytest.approx(float(rollout["next", "reward"].sum()))
        assert rec.collided == bool(rollout[-1]["next", "collided"])
    # and whole episodes agree with the TorchRL recorder for a world-state policy
    rec_trl = record_episodes(cfg, ScriptedDriver(), episodes=1, seed=seeds[0], keep_stable=False)
    ours = run_job(DriverActor(ScriptedDriver), Job(cfg, "non_goal", [(0, seeds[0])])).records[0]
    e = rec_trl.episodes[0]
    assert (e.steps, e.collided, e.reached_target) == (ours.steps, ours.collided, ours.reached_target)


def test_greedy_actor_acts_like_the_checkpoint_policy():
    torch.manual_seed(0)
    net = QNetwork()
    env = LaneChangeEnv(config={"vehicles_count": 5})
    obs = []
    for seed in range(6):
        frames = [env.reset(seed=seed)[0]]
        for a in range(3):
            frames.append(env.step((seed + a) % N_ACTIONS)[0])
        obs.append(np.concatenate(frames))
    pixels = np.stack(obs)
    batched = GreedyActor(net).act(list(range(6)), [env] * 6, pixels)
    single = [GreedyQPolicy(net).act(env, p) for p in pixels]
    assert batched.tolist() == single
    with torch.no_grad():  # channels-last inference gives the plain network's Q-values
        fast = GreedyActor(net).net(torch.from_numpy(pixels).contiguous(memory_format=torch.channels_last))
        assert torch.allclose(fast, net(torch.from_numpy(pixels)), atol=1e-6)
    assert next(net.parameters()).is_contiguous()  # the network given is left as it was


def _jobs() -> list[Job]:
    cfg = protocol_env({}, ProtocolConfig(duration=30), "random")
    return [Job(cfg, "random", list(enumerate(scenario_seeds(3, 6)))),
            Job({**cfg, "initial_lane": "non_goal"}, "non_goal", list(enumerate(scenario_seeds(3, 6))))]


def test_batches_give_the_same_records_as_one_episode_at_a_time():
    for actor in (lambda: DriverActor(RandomPolicy, seeded=True), lambda: GreedyActor(QNetwork())):
        torch.manual_seed(0)
        a = actor()
        one = run_jobs(a, _jobs(), batch=1).records
        assert run_jobs(a, _jobs(), batch=4).records == one
        assert [(r.initial_lane, r.episode) for r in one] == \
            [(lane, i) for lane in ("random", "non_goal") for i in range(6)]


class InlinePool:
    """Stands in for the process pool: runs each piece at once on a pickled copy of its
    arguments, which is what a worker process receives."""

    def __init__(self, *args, **kwargs) -> None:
        self.pieces = 0

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> bool:
        return False

    def submit(self, fn, *args, **kwargs):
        self.pieces += 1
        future: Future = Future()
        args, kwargs = pickle.loads(pickle.dumps((args, kwargs)))
        future.set_result(fn(*args, **kwargs))
        return future


def test_work_split_over_workers_comes_back_whole_and_in_order(monkeypatch):
    monkeypatch.setattr(runner, "ProcessPoolExecutor", InlinePool)
    for make in (lambda: DriverActor(RandomPolicy, seeded=True), lambda: GreedyActor(QNetwork())):
        torch.manual_seed(0)
        actor = make()
        assert run_jobs(actor, _jobs(), workers=3, batch=2).records == run_jobs(actor, _jobs()).records
    assert sum(len(j.episodes) for j in runner.split(_jobs(), 8)) == 12
    # the recorded Q-values come back from the workers too, in the records' order
    split = run_jobs(actor, _jobs(), workers=3, batch=2, engine=False, record=True)
    whole = run_jobs(actor, _jobs(), engine=False, record=True)
    assert [(t.initial_lane, t.episode) for t in split.traces] == \
        [(r.initial_lane, r.episode) for r in whole.records]
    for a, b in zip(split.traces, whole.traces, strict=True):
        np.testing.assert_allclose(a.q, b.q, rtol=1e-5, atol=1e-5)


@pytest.mark.slow
def test_worker_processes_give_the_same_records():
    actor = DriverActor(RandomPolicy, seeded=True)
    assert run_jobs(actor, _jobs(), workers=2, batch=2).records == run_jobs(actor, _jobs()).records


# ------------------------------------------------------------------------ entry point
def test_evaluate_checkpoint_writes_into_the_run_folder(compose_cfg, tmp_path):
    run = fake_run(tmp_path / "sweep", compose_cfg, mode="B", seed=3, env=["env.lanes_count=3"])
    cfg = compose_cfg("evaluate", [f"policy.run={tmp_path / 'sweep'}", *SMALL])
    [result] = evaluate(cfg, out_dir=tmp_path / "unused")
    assert result.path == run / "eval" and result.name == "B" and result.unit == "seed 3"
    doc = json.loads((run / "eval" / "eval.json").read_text())
    assert doc["seeds"] == scenario_seeds(0, 3) and doc["protocol"]["duration"] == 25
    assert doc["env"]["lanes_count"] == 3  # the run's own env, the protocol's rules on top
    assert doc["env"]["vehicles_count"] == [0, 5] and doc["meta"]["train_seed"] == 3
    with (run / "eval" / "episodes.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [(r["initial_lane"], int(r["seed"])) for r in rows] == \
        [(lane, s) for lane in ("random", "non_goal") for s in scenario_seeds(0, 3)]
    assert all(int(r["steps"]) <= 25 for r in rows)
    for lane in ("random", "non_goal"):
        lane_rows = [r for r in rows if r["initial_lane"] == lane]
        assert doc["scores"][lane]["survival"] == sum(int(r["survived"]) for r in lane_rows)
        assert doc["scores"][lane]["goal"] == sum(int(r["reached_target"]) for r in lane_rows)
    # the same greedy policy evaluated again gives the same episodes
    evaluate(cfg, out_dir=tmp_path / "unused")
    with (run / "eval" / "episodes.csv").open() as f:
        assert list(csv.DictReader(f)) == rows
    net, _ = load_qnet(run)
    assert net is not None


def test_other_test_traffic_goes_beside_eval_and_another_protocol_is_not_replaced(compose_cfg, tmp_path):
    from memrl.errors import UserError

    def ev(overrides: list[str]) -> list:
        return evaluate(compose_cfg("evaluate", overrides), out_dir=tmp_path / "unused")

    run = fake_run(tmp_path / "run", compose_cfg, seed=1)
    pool = fake_run(tmp_path / "pool", compose_cfg, seed=2)
    ev([f"policy.run={run}", *SMALL])
    constant = (run / "eval" / "eval.json").read_bytes()
    [mixed] = ev([f"policy.run={run}", "opponent=mixed", f"env.opponent.pool=[{pool}]", *SMALL])
    assert mixed.path == run / "eval_mixed" and mixed.protocol["opponent"]["type"] == "mixed"
    doc = json.loads((run / "eval_mixed" / "eval.json").read_text())
    assert doc["meta"]["policy_config"]["subdir"] == "eval_mixed"
    assert (run / "eval" / "eval.json").read_bytes() == constant  # the constant-traffic folder untouched
    longer = [f"policy.run={run}", *SMALL, "protocol.duration=30"]
    refusal = r"eval holds an evaluation under another protocol \(differs in: duration\)"
    with pytest.raises(UserError, match=refusal):
        ev(longer)
    assert (run / "eval" / "eval.json").read_bytes() == constant
    [elsewhere] = ev([*longer, "policy.subdir=eval_30"])
    assert elsewhere.path == run / "eval_30" and (run / "eval" / "eval.json").read_bytes() == constant
    [replaced] = ev([*longer, "overwrite=true"])
    assert replaced.path == run / "eval"
    assert json.loads((run / "eval" / "eval.json").read_text())["protocol"]["duration"] == 30


@pytest.mark.parametrize("policy", ["scripted", "random"])
def test_untrained_policies_are_evaluated_into_the_output_folder(compose_cfg, tmp_path, policy):
    [result] = evaluate(compose_cfg("evaluate", [f"policy={policy}", *SMALL]), out_dir=tmp_path)
    assert result.name == policy and (tmp_path / "eval.json").is_file()
    assert json.loads((tmp_path / "eval.json").read_text())["meta"]["policy_config"]["name"] == policy
    if policy == "scripted":  # the stable driver does not crash in a short episode
        assert all(s.survival_score == 100.0 for s in result.scores.values())


def test_policy_group_configs_instantiate(compose_cfg, tmp_path):
    fake_run(tmp_path, compose_cfg)
    for name in ("scripted", "random", "human"):
        source = instantiate(compose_cfg("evaluate", [f"policy={name}"]).policy)
        assert source.candidates()[0].name == name
    src = instantiate(compose_cfg("evaluate", [f"policy.run={tmp_path}"]).policy)
    assert [c.name for c in src.candidates()] == ["Default"]
    with pytest.raises(Exception, match="no finished training run"):  # wrapped by Hydra
        instantiate(compose_cfg("evaluate", [f"policy.run={tmp_path / 'default_0' / 'checkpoints'}"]).policy)


def test_bad_protocol_fails_at_start(compose_cfg, tmp_path):
    with pytest.raises(ProtocolError, match="episodes"):
        evaluate(compose_cfg("evaluate", ["policy=random", "protocol.episodes=0"]), out_dir=tmp_path)


# ---------------------------------------------------------------------------- human
@pytest.fixture
def pg(monkeypatch):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    import pygame

    pygame.display.init()
    pygame.event.clear()
    yield pygame
    pygame.display.quit()


def test_human_at_the_keyboard_fills_the_human_row(pg, compose_cfg, tmp_path):
    cfg = compose_cfg("evaluate", ["policy=human", "policy.person=ann", "policy.driver.fps=0",
                                   "policy.driver.controls=literal",
                                   "policy.driver.wait_for_start=false", *SMALL, "workers=2"])
    pg.event.post(pg.event.Event(pg.KEYDOWN, key=pg.K_LEFT))  # held: the car turns into a wall
    [result] = evaluate(cfg, out_dir=tmp_path)
    assert result.name == "human" and result.unit == "ann"
    assert sum(s.episodes for s in result.scores.values()) == 6
    assert result.scores["non_goal"].survival < 3  # steering hard left for 25 steps ends in a crash


def test_human_can_stop_and_keeps_finished_episodes(pg, tmp_path):
    cfg = protocol_env({}, ProtocolConfig(duration=10), "random")
    driver = KeyboardDriver(fps=0, wait_for_start=False)
    calls = {"n": 0}
    real_act = driver.act

    def act(env, pixels):
        calls["n"] += 1
        if calls["n"] == 15:  # Esc during the second episode
            pg.event.post(pg.event.Event(pg.KEYDOWN, key=pg.K_ESCAPE))
        return real_act(env, pixels)

    driver.act = act  # type: ignore[method-assign]
    actor = HumanSource(driver).candidates()[0].actor
    res = run_jobs(actor, [Job(cfg, "random", list(enumerate(scenario_seeds(0, 4))))])
    assert res.stopped_early and [r.episode for r in res.records] == [0]


# ------------------------------------------------------------------------- periodic
def test_periodic_eval_gives_the_scores_of_a_few_greedy_episodes():
    torch.manual_seed(0)
    net = QNetwork()
    before = {k: v.clone() for k, v in net.state_dict().items()}
    env = {"duration": 15, "vehicles_count": 5}
    m = periodic_eval(net, env, episodes=3, seed=1)
    for lane in ("random", "non_goal"):
        assert 0 <= m[f"survival_{lane}"] <= 100 and 0 <= m[f"goal_{lane}"] <= 100
        assert 1 <= m[f"steps_{lane}"] <= 15
    again = periodic_eval(net, env, episodes=3, seed=1)
    assert {k: v for k, v in m.items() if k != "wall_s"} == {k: v for k, v in again.items() if k != "wall_s"}
    assert all(torch.equal(before[k], v) for k, v in net.state_dict().items())
    assert set(periodic_eval(net, env, episodes=2, seed=1, initial_lanes=["non_goal"])) == \
        {"survival_non_goal", "goal_non_goal", "return_non_goal", "steps_non_goal", "wall_s"}


class Logger:
    def __init__(self) -> None:
        self.points: list[tuple[str, float, int]] = []

    def log_scalar(self, name, value, step) -> None:
        self.points.append((name, value, step))


def test_periodic_evaluation_by_env_steps_at_each_multiple_crossed(tmp_path):
    """``unit: env_steps``, every 100: a row at the first call past 100, 200, ... (one for a
    call that crosses two), none from episode ends; a resume keeps the rows up to its
    checkpoint and goes on from the checkpoint's env steps."""
    net = QNetwork()
    pe = PeriodicEvaluation({"every": 100, "unit": "env_steps", "episodes": 1}, {"duration": 5},
                            tmp_path)
    assert pe.after_episode(net, 100, 100) is None
    frames = [16, 96, 112, 128, 304, 320, 400]
    done = [pe.after_steps(net, i, f) is not None for i, f in enumerate(frames)]
    assert done == [False, False, True, False, True, False, True]
    with (tmp_path / PERIODIC_CSV).open() as f:
        assert [(int(r["episode"]), int(r["env_steps"])) for r in csv.DictReader(f)] == [
            (2, 112), (4, 304), (6, 400)]
    pe.rewind(5, 320)  # the checkpoint came after the row at 304, before the one at 400
    with (tmp_path / PERIODIC_CSV).open() as f:
        assert [int(r["env_steps"]) for r in csv.DictReader(f)] == [112, 304]
    assert pe.after_steps(net, 5, 336) is None and pe.after_steps(net, 6, 400) is not None


def test_periodic_evaluation_as_the_training_loop_would_call_it(tmp_path):
    torch.manual_seed(0)
    net, logger = QNetwork(), Logger()
    pe = PeriodicEvaluation({"every": 3, "episodes": 2}, {"duration": 10}, tmp_path, logger)
    rng_before = (torch.get_rng_state(), np.random.get_state()[1].copy(), random.getstate())
    rows = [pe.after_episode(net, ep, 100 * ep) for ep in range(1, 7)]
    assert [r is not None for r in rows] == [False, False, True, False, False, True]
    assert torch.equal(rng_before[0], torch.get_rng_state())  # exact resume is not disturbed
    assert np.array_equal(rng_before[1], np.random.get_state()[1]) and rng_before[2] == random.getstate()
    with (tmp_path / PERIODIC_CSV).open() as f:
        table = list(csv.DictReader(f))
    assert [int(r["episode"]) for r in table] == [3, 6] and [int(r["env_steps"]) for r in table] == [300, 600]
    assert float(table[0]["survival_non_goal"]) == rows[2]["survival_non_goal"]
    assert ("eval/goal_random", rows[5]["goal_random"], 600) in logger.points
    assert all(pe.after_steps(net, 6, f) is None for f in (700, 900))  # unit: episodes
    pe.rewind(4, 450)
    with (tmp_path / PERIODIC_CSV).open() as f:
        assert [int(r["episode"]) for r in csv.DictReader(f)] == [3]
    off = PeriodicEvaluation(None, {}, tmp_path / "off")
    assert off.after_episode(net, 3, 300) is None and not (tmp_path / "off").exists()
