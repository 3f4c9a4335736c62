"""Evaluation on the batched engine gives exactly the gym-env runner's records: the Table III
protocol's two initial lanes, a few random Q-networks, constant and learned traffic; and
periodic evaluation and stage-1 drives, which run through it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from memrl.dqn.stage1 import drive_check, drive_counts
from memrl.envs.vehicles import IDLE
from memrl.evaluation import engine_runner, runner
from memrl.evaluation.periodic import periodic_eval
from memrl.evaluation.policies import DriverActor, GreedyActor
from memrl.evaluation.protocol import ProtocolConfig, protocol_env, scenario_seeds
from memrl.evaluation.runner import Job, run_jobs
from memrl.modules.policy import FrameStack, GreedyPolicy, RandomPolicy
from memrl.modules.qnet import QNetwork
from tests.helpers import save_pool


def qnet(seed: int, idle_bias: float = 0.0) -> QNetwork:
    """A fresh Q-network with spread Q-values (no near-ties that the batch composition could
    flip); ``idle_bias`` favours keeping speed and curvature: longer episodes, which reach the
    target lane or the time limit."""
    torch.manual_seed(seed)
    net = QNetwork()
    with torch.no_grad():
        net.head[-1].weight.mul_(30.0)
        net.head[-1].bias[IDLE] += idle_bias
    return net


def protocol_jobs(episodes: int, duration: int, **protocol) -> list[Job]:
    """The Table III protocol's jobs (both initial lanes, the test scenes), shortened."""
    p = ProtocolConfig(episodes=episodes, duration=duration, **protocol)
    seeds = list(enumerate(scenario_seeds(p.seed, episodes)))
    return [Job(protocol_env({}, p, lane), lane, seeds) for lane in p.initial_lanes]


@pytest.fixture(scope="module")
def pool(tmp_path_factory):
    return save_pool(tmp_path_factory.mktemp("pool"), head_scale=100.0)


NETS = [(0, 0.0), (1, 0.0), (2, 40.0), (3, 40.0)]
CASES = [(NETS[0], "constant"), (NETS[1], "learned"), (NETS[2], "constant_5"), (NETS[2], "learned"),
         (NETS[3], "mixed_0_3")]


@pytest.mark.parametrize(("net", "traffic"), CASES, ids=[f"seed{n[0]}-{t}" for n, t in CASES])
def test_engine_records_equal_the_gym_runner_records(net, traffic, pool):
    opponent = {"type": "constant"} if traffic.startswith("constant") else \
        {"type": traffic.split("_")[0], "pool": pool, "epsilon": 0.1}
    counts = {"constant": [0, 5], "constant_5": [5, 5], "learned": [0, 5], "mixed_0_3": [0, 3]}[traffic]
    episodes = 8 if opponent["type"] == "constant" else 5  # one forward per learned car in gym envs
    jobs = protocol_jobs(episodes, 60 if episodes == 8 else 40, opponent=opponent, vehicles_count=counts)
    actor = GreedyActor(qnet(*net))
    gym = run_jobs(actor, jobs, engine=False).records
    assert [(r.initial_lane, r.episode) for r in gym] == [(lane, i) for lane in ("random", "non_goal")
                                                           for i in range(episodes)]
    assert run_jobs(actor, jobs).records == gym  # all episodes of a job at once
    assert run_jobs(actor, jobs, engine_batch=3).records == gym  # finished envs take the next episode


def test_the_records_cover_every_ending(pool):
    """The cases above see crashes, truncations, reached target lanes and several car counts."""
    recs = []
    for net in NETS:
        recs += run_jobs(GreedyActor(qnet(*net)), protocol_jobs(8, 60)).records
    assert {r.collided for r in recs} == {True, False} and {r.reached_target for r in recs} == {True, False}
    assert any(r.steps == 60 for r in recs) and any(r.steps < 60 for r in recs)
    assert {r.start_lane == r.target_lane for r in recs} == {True, False}
    assert len({r.vehicles for r in recs}) > 3


def test_the_engine_path_is_taken_for_tensor_actors_only(monkeypatch):
    calls = []
    real = engine_runner.run_jobs_on_engine

    def spy(*args, **kwargs):
        calls.append(kwargs["device"])
        return real(*args, **kwargs)

    monkeypatch.setattr(runner, "run_jobs_on_engine", spy)
    jobs = protocol_jobs(2, 10)
    run_jobs(GreedyActor(qnet(0)), jobs)
    assert calls == [torch.device("cpu")]
    run_jobs(DriverActor(RandomPolicy, seeded=True), jobs)
    rgb = [Job({**j.env, "bev": {"grayscale": False}}, j.initial_lane, j.episodes) for j in jobs]
    run_jobs(GreedyActor(QNetwork(frames=12)), rgb)  # RGB frames: only the gym env draws them
    assert not engine_runner.engine_can_run(Job({"frame_stack": 4}, "random", []))  # gym-stacked
    assert not engine_runner.engine_can_run(Job({"simulation_frequency": 10}, "random", []))  # highway-env's
    assert len(calls) == 1
    with pytest.raises(TypeError, match="tensor_policy"):
        real(DriverActor(RandomPolicy), jobs)


@pytest.mark.parametrize("net", NETS[:3])
def test_periodic_eval_and_stage1_drives_are_the_same_through_the_engine(net, monkeypatch):
    q = qnet(*net)
    env = {"duration": 50, "vehicles_count": 5}
    new = periodic_eval(q, env, episodes=6, seed=2)
    counts = drive_counts(q, env, scenario_seeds(0, 8, domain="stage1"))
    check = drive_check(q, env, 8)
    monkeypatch.setattr(GreedyActor, "tensor_policy", False)  # today's gym-env path
    old = periodic_eval(q, env, episodes=6, seed=2)
    assert {k: v for k, v in new.items() if k != "wall_s"} == {k: v for k, v in old.items() if k != "wall_s"}
    assert drive_counts(q, env, scenario_seeds(0, 8, domain="stage1")) == counts
    assert drive_check(q, env, 8) == check


def test_greedy_policy_is_one_policy_for_one_stack_and_for_a_batch():
    net = qnet(5)
    pixels = torch.randint(0, 256, (6, 4, 84, 84), dtype=torch.uint8)
    policy = GreedyPolicy(net)
    batch = policy.act_batch(pixels)
    assert [policy.act(None, p.numpy()) for p in pixels] == batch.tolist()  # type: ignore[arg-type]
    assert torch.equal(batch, net(pixels).argmax(-1))
    chunked = GreedyPolicy(net, cpu_chunk=4).q_values(pixels)  # chunks, strided-maximum pools
    assert torch.allclose(chunked, net(pixels), atol=1e-5, rtol=0)
    assert torch.allclose(GreedyPolicy(net, cpu_chunk=None).q_values(pixels), net(pixels), atol=1e-5, rtol=0)
    assert next(net.parameters()).is_contiguous()  # the network given is left as it was


def test_frame_stack_repeats_the_first_frame_and_drops_the_oldest():
    stack = FrameStack(3)
    frames = [np.full((1, 2, 2), k, np.uint8) for k in range(5)]
    assert stack.reset(frames[0])[:, 0, 0].tolist() == [0, 0, 0]
    for k in range(1, 5):
        stack.push(frames[k])
    assert stack.frames is not None and stack.frames[:, 0, 0].tolist() == [2, 3, 4]


def test_bench_eval_times_both_runners_on_the_same_episodes(compose_cfg, tmp_path):
    from memrl.bench import bench

    cfg = compose_cfg("bench", ["benchmarks=[eval]", "eval.episodes=3", "eval.duration=20",
                                "eval.idle_bias=[0,40]", "eval.checkpoints=2"])
    res = bench(cfg, tmp_path)["eval"]
    assert res["episodes"] == 6 and res["threads"] == 1 and res["device"] == "cpu"
    for name in ("fresh_qnet", "fresh_qnet_idle_bias_40"):
        row = res[name]
        assert row["same_records"] is True
        assert row["today_runner"]["env_steps"] == row["engine_runner"]["env_steps"]
        assert row["ratio"] == pytest.approx(row["today_runner"]["wall_s"] / row["engine_runner"]["wall_s"])
        assert row["engine_runner"]["forward_samples"] == row["engine_runner"]["env_steps"]
        rec = row["engine_runner_recorded"]  # the same episodes, each step's Q-values kept
        assert row["recorded_same_records"] is True and rec["traces"] == 6 and rec["summarize_s"] >= 0
        assert row["record_cost"] == pytest.approx(rec["wall_s"] / row["engine_runner"]["wall_s"])
        k = row["k_checkpoints"]  # 2 networks alone, then together: the same records
        assert k["k"] == 2 and k["same_records"] is True and k["env_steps"] >= 2 * 6
        assert k["speedup"] == pytest.approx(k["alone_s"] / k["together_s"])


def test_recording_and_the_deploy_baseline_drive_the_greedy_policy_as_the_evaluation_does():
    """One greedy policy and one frame stack: the recorder's direct drive and the deploy
    baseline's simulator episodes end as the evaluation's records of the same scenes."""
    from memrl.control.baseline import simulator_episode
    from memrl.data.recording import drive_episodes
    from memrl.envs.lane_change import LaneChangeEnv

    net = qnet(2, 40.0)
    env_cfg = {"duration": 40, "vehicles_count": [0, 4], "initial_lane": "non_goal"}
    seeds = [11, 12, 13, 14]
    recs = run_jobs(GreedyActor(net), [Job(env_cfg, "non_goal", list(enumerate(seeds)))]).records
    stats = drive_episodes(env_cfg, GreedyPolicy(net), seeds)
    assert [(s.steps, s.episode_return, s.collided, s.reached_target) for s in stats] == \
        [(r.steps, r.episode_return, r.collided, r.reached_target) for r in recs]
    env = LaneChangeEnv(config=env_cfg)
    runs = [simulator_episode(env, GreedyPolicy(net), s) for s in seeds]
    assert [(r["collided"], r["reached_target"]) for r in runs] == \
        [(r.collided, r.reached_target) for r in recs]


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message without CUDA")
def test_cuda_without_cuda_is_one_clear_error():
    from memrl.envs.batched import BatchedEnvError

    with pytest.raises(BatchedEnvError, match="CUDA is not available"):
        run_jobs(GreedyActor(qnet(0)), protocol_jobs(2, 10), device="cuda")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_engine_on_cuda_gives_the_gym_runner_records(pool):
    jobs = protocol_jobs(6, 40, opponent={"type": "mixed", "pool": pool}, vehicles_count=[0, 5])
    actor = GreedyActor(qnet(2, 40.0))
    gym = run_jobs(actor, jobs, engine=False).records
    assert run_jobs(actor, jobs, device="cuda").records == gym


def test_a_replayed_episode_with_a_step_hook_is_the_evaluated_one():
    """Figures replay one episode on a gym env with a hook (rendering): it is the episode
    the engine evaluated."""
    from memrl.evaluation.runner import run_job

    net = qnet(2, 40.0)
    jobs = protocol_jobs(3, 40)
    recs = run_jobs(GreedyActor(net), jobs).records
    views: list[np.ndarray] = []
    one = run_job(GreedyActor(net), Job(jobs[1].env, "non_goal", [jobs[1].episodes[2]]), batch=1,
                  hook=lambda env, px, action, rec: views.append(px[-1].copy())).records[0]
    assert one == recs[3 + 2]
    assert len(views) == one.steps + 1


def test_k_actors_on_one_engine_get_the_records_each_gets_alone():
    """Three checkpoints on one engine per job: each actor's records (and, all episodes at once,
    its recorded Q-values bit for bit: its rows are the batch it gets alone) are its own run's;
    with 2 envs per job and actor, envs change hands between actors and the records still match."""
    actors = [GreedyActor(qnet(*net), gamma=0.95) for net in NETS[:3]]
    jobs = protocol_jobs(6, 60)
    alone = [engine_runner.run_jobs_on_engine(a, jobs, record=True) for a in actors]
    together = engine_runner.run_actors_on_engine(actors, jobs, record=True)
    key = lambda r: (r.initial_lane, r.episode)  # noqa: E731
    for a, t in zip(alone, together, strict=True):
        assert len(a.records) == 12 and sorted(t.records, key=key) == sorted(a.records, key=key)
        ta, tt = sorted(a.traces, key=key), sorted(t.traces, key=key)
        assert len(ta) == len(tt) == 12
        for x, y in zip(ta, tt, strict=True):
            assert np.array_equal(x.q, y.q) and np.array_equal(x.actions, y.actions), key(x)
    assert len({tuple(r.steps for r in sorted(a.records, key=key)) for a in alone}) == 3  # the actors differ
    small = engine_runner.run_actors_on_engine(actors, jobs, batch=2)
    for a, t in zip(alone, small, strict=True):
        assert sorted(t.records, key=key) == sorted(a.records, key=key) and not t.traces


def test_evaluating_k_candidates_together_writes_the_folders_each_writes_alone(tmp_path):
    """``evaluate_candidates``: three greedy networks on one engine per lane give each the
    eval.json (scores, records, crash-sight tables) and episodes.csv of its own evaluation;
    a candidate whose env differs is evaluated on its own."""
    import json

    from memrl.evaluation.policies import Candidate
    from memrl.evaluation.session import evaluate_candidate, evaluate_candidates

    protocol = ProtocolConfig(episodes=4, duration=50)
    env = {"vehicles_count": [0, 5]}

    def cands(where, envs=(env, env, env)):
        return [Candidate(f"n{i}", GreedyActor(qnet(*net), gamma=0.95), env=dict(e), out_dir=where / f"n{i}")
                for i, (net, e) in enumerate(zip(NETS[:3], envs, strict=True))]

    alone = [evaluate_candidate(c, protocol) for c in cands(tmp_path / "alone")]
    made = evaluate_candidates(cands(tmp_path / "together"), protocol, share=True)
    volatile = ("wall_s", "batch", "together")  # the gym path's lockstep batch; the K that shared the engine

    def doc(folder):
        return {k: v for k, v in json.loads((folder / "eval.json").read_text()).items() if k not in volatile}

    for a, t in zip(alone, made, strict=True):
        assert doc(t.path) == doc(a.path) and doc(a.path)["crash_sight"] is not None
        assert (t.path / "episodes.csv").read_text() == (a.path / "episodes.csv").read_text()
        assert json.loads((t.path / "eval.json").read_text())["together"] == 3
    for d in evaluate_candidates(cands(tmp_path / "default"), protocol):  # share off: each alone
        assert "together" not in json.loads((d.path / "eval.json").read_text())
    mixed = cands(tmp_path / "mixed", (env, env, {**env, "bev": {"path_time": 0.0}}))  # other frames
    from memrl.evaluation.session import _plan, together

    assert not together(mixed, [_plan(c, protocol, None, None, None) for c in mixed])
