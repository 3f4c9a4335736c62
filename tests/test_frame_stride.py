"""``env.frame_stride`` k: the stack at step t is the frames of steps t-3k, t-2k, t-k, t (oldest
first; the reset frame for steps before 0) in every engine, and the engines agree exactly."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs, step_mdp

from memrl.envs import ENV_ID
from memrl.envs.batched import BatchedLaneChange
from memrl.envs.config import EnvConfigError, validate_env_config
from memrl.envs.lane_change import LaneChangeEnv
from memrl.envs.stride import history_length, stack_positions
from memrl.envs.torchrl_env import make_env, unwrap
from memrl.modules.policy import FrameStack
from tests.batched_helpers import STATE_ATOL, car_states, compare, random_actions

NON_GOAL = {"initial_lane": "non_goal", "vehicles_count": [0, 5]}
S = 4


def test_history_spans_the_stack():
    assert history_length(4, 1) == 4 and history_length(4, 3) == 10
    assert stack_positions(4, 3) == [0, 3, 6, 9]


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "2"])
def test_bad_frame_stride_names_the_key(bad):
    with pytest.raises(EnvConfigError, match="'frame_stride': must be (an int )?>= 1"):
        validate_env_config({"frame_stride": bad})


# ------------------------------------------------------------------------- hand check
def _expected(newest: list[np.ndarray], t: int, k: int) -> np.ndarray:
    """The contract: frames t-3k, t-2k, t-k, t, each clamped to the reset frame (step 0)."""
    return np.stack([newest[max(t - (S - 1 - j) * k, 0)] for j in range(S)])


@pytest.mark.parametrize("k", [2, 3])
def test_every_engine_stacks_frames_t_minus_jk_padded_with_the_reset_frame(k):
    """20 steps of 3 envs: at each step every engine's stack is, by hand, its own newest frames
    of steps t-3k, t-2k, t-k, t (the reset frame for negative times)."""
    config = {"frame_stride": k, "vehicles_count": 3, "bev": {"path_length": 20.0}}
    seeds, steps = [0, 1, 2], 20
    rng = np.random.default_rng(2)  # actions under which no car crashes in these 20 steps
    actions = np.where(rng.random((steps, len(seeds))) < 0.3, rng.integers(9, size=(steps, len(seeds))), 4)
    engine = BatchedLaneChange(config, len(seeds))
    engine.reset(seeds=seeds)
    gym_envs = [LaneChangeEnv(config={**config, "frame_stack": S}) for _ in seeds]
    gym_obs = [env.reset(seed=s)[0] for env, s in zip(gym_envs, seeds, strict=True)]
    pipes = [make_env(config) for _ in seeds]
    tds = [p.reset(seed=s) for p, s in zip(pipes, seeds, strict=True)]
    singles = [LaneChangeEnv(config=config) for _ in seeds]  # frame_stack 1, stacked by FrameStack
    stacks = [FrameStack(S, k) for _ in seeds]
    hand = [st.reset(env.reset(seed=s)[0]) for st, env, s in zip(stacks, singles, seeds, strict=True)]
    newest: list[list[np.ndarray]] = [[] for _ in seeds]  # per env, its frame of each step
    for t in range(steps + 1):
        if t > 0:
            engine.step(torch.as_tensor(actions[t - 1]))
            for i in range(len(seeds)):
                a = int(actions[t - 1, i])
                gym_obs[i] = gym_envs[i].step(a)[0]
                tds[i]["action"] = torch.tensor(a)
                tds[i] = step_mdp(pipes[i].step(tds[i]))
                hand[i] = stacks[i].push(singles[i].step(a)[0])
        obs = engine.observation().numpy()
        for i in range(len(seeds)):
            newest[i].append(engine.newest_frame()[i].numpy().copy())
            want = _expected(newest[i], t, k)
            assert np.array_equal(obs[i], want), (i, t)
            for name, got in (("gym", gym_obs[i]), ("torchrl", tds[i]["pixels"].numpy()), ("hand", hand[i])):
                assert np.array_equal(got, want), (name, i, t)
            assert not unwrap(pipes[i]).vehicle.crashed  # no episode ended: one stack throughout
    for frames in newest:  # the check has teeth: every step's frame differs from every other
        assert len({f.tobytes() for f in frames}) == steps + 1


# ----------------------------------------------------------- engines equal, with resets
def _pipeline_vs_engine(config: dict, seeds: list[int], steps: int, auto_reset: bool,
                        p_random: float = 0.5) -> dict[str, int]:
    """Reference envs through the TorchRL pipeline (``make_env``: CatFrames + EveryKthFrame) and
    one batched engine, same seeds and actions: identical stacks, rewards, flags; states within
    ``STATE_ATOL``; finished episodes reset in both (seedless: each env's generator goes on)."""
    n = len(seeds)
    pipes = [make_env(config) for _ in seeds]
    tds = [p.reset(seed=s) for p, s in zip(pipes, seeds, strict=True)]
    engine = BatchedLaneChange(config, n, "cpu", S)
    engine.reset(seeds=seeds)
    obs = engine.observation().numpy()
    for i in range(n):
        assert np.array_equal(tds[i]["pixels"].numpy(), obs[i])
    rng = np.random.default_rng(seeds[0])
    seen = {"steps": 0, "resets": 0, "crashes": 0}
    for _ in range(steps):
        actions = np.where(rng.random(n) < p_random, rng.integers(9, size=n), 4)
        out = engine.step(torch.as_tensor(actions), auto_reset=auto_reset)
        obs, state, present = engine.observation().numpy(), engine.state.numpy(), engine.present.numpy()
        final = {} if out.reset_ids is None else {
            i: out.final_observation[row].numpy() for row, i in enumerate(out.reset_ids.tolist())}
        done = []
        for i, pipe in enumerate(pipes):
            tds[i]["action"] = torch.tensor(int(actions[i]))
            td = pipe.step(tds[i])
            nxt = td["next"]
            assert np.array_equal(nxt["pixels"].numpy(), final.get(i, obs[i])), (i, seen["steps"])
            assert nxt["reward"].item() == np.float32(out.reward[i].item())
            for key in ("terminated", "truncated", "collided", "on_target_lane", "reached_target"):
                assert bool(nxt[key]) == bool(getattr(out, key)[i]), key
            if i not in final:
                got, want = state[i][present[i]], car_states(unwrap(pipe))
                assert got.shape == want.shape and float(np.abs(got - want).max()) <= STATE_ATOL
            seen["steps"] += 1
            if bool(nxt["done"]):
                seen["crashes"] += int(nxt["terminated"])
                done.append(i)
                tds[i] = pipe.reset()
            else:
                tds[i] = step_mdp(td)
        assert sorted(final) == (done if auto_reset else [])
        if done and not auto_reset:
            engine.reset(done)
        if done:
            obs = engine.observation().numpy()
            for i in done:
                assert np.array_equal(tds[i]["pixels"].numpy(), obs[i])
                assert (obs[i] == obs[i, -1]).all()  # a new episode: the first frame throughout
            seen["resets"] += len(done)
    return seen


def test_gym_stack_and_batched_engine_agree_at_stride_3_16_seeds_300_steps():
    """The reference env's own stack (``frame_stack: 4``) against the engine's: 16 seeds x 300
    steps at k = 3 among 0-5 cars, crashes into cars and walls, auto-resets inside the step."""
    tally = compare({**NON_GOAL, "frame_stack": S, "frame_stride": 3}, list(range(16)), 300,
                    random_actions(1.0), auto_reset=True)
    assert tally.steps == 16 * 300 and tally.resets > 16 and tally.wall_hits > 0


@pytest.mark.parametrize(("k", "auto_reset"), [(3, True), (2, False)])
def test_torchrl_pipeline_and_batched_engine_agree_with_resets(k, auto_reset):
    """The TorchRL pipeline (CatFrames + EveryKthFrame) against the engine; its per-step cost
    keeps this short in the default suite (the 16 x 300 version is marked slow)."""
    seen = _pipeline_vs_engine({**NON_GOAL, "frame_stride": k}, list(range(100, 103)), 60, auto_reset,
                               p_random=1.0)
    assert seen["resets"] > 0


def test_gym_stack_and_batched_engine_agree_at_stride_2():
    tally = compare({**NON_GOAL, "frame_stack": S, "frame_stride": 2}, list(range(16, 24)), 120,
                    random_actions(0.5))
    assert tally.resets > 0


@pytest.mark.slow
@pytest.mark.parametrize("k", [2, 3])
def test_pipeline_gym_stack_and_engine_agree_16_seeds_300_steps(k):
    seen = _pipeline_vs_engine({**NON_GOAL, "frame_stride": k}, list(range(200, 216)), 300, auto_reset=k == 3)
    assert seen["steps"] == 16 * 300 and seen["resets"] > 16
    tally = compare({**NON_GOAL, "frame_stack": S, "frame_stride": k}, list(range(300, 316)), 300,
                    random_actions(1.0), auto_reset=k == 2)
    assert tally.steps == 16 * 300 and tally.resets > 16


def test_gym_vector_face_equals_sync_vector_env_at_stride_3():
    n, config = 4, {**NON_GOAL, "frame_stack": S, "frame_stride": 3}
    ref = gym.vector.SyncVectorEnv([lambda: LaneChangeEnv(config=config) for _ in range(n)])
    vec = gym.make_vec(ENV_ID, num_envs=n, vectorization_mode="vector_entry_point", config=config)
    assert vec.single_observation_space.shape == (S, 84, 84)
    assert np.array_equal(ref.reset(seed=11)[0], vec.reset(seed=11)[0])
    rng, finished = np.random.default_rng(0), 0
    for _ in range(80):
        actions = rng.integers(9, size=n)
        a, b = ref.step(actions), vec.step(actions)
        for x, y in zip(a[:4], b[:4], strict=True):
            assert np.array_equal(x, y)
        finished += int((a[2] | a[3]).sum())
    assert finished > 0


def test_torchrl_batched_face_gives_the_engine_stacks():
    config = {**NON_GOAL, "frame_stride": 3}
    env = make_env(config, num_envs=3, seed=5)
    check_env_specs(env)
    env.set_seed(5)
    td = env.rollout(40, break_when_any_done=False)
    engine = BatchedLaneChange(config, 3)
    engine.reset(seeds=[5, 6, 7])
    rng_actions = td["action"]
    assert np.array_equal(td["pixels"][:, 0].numpy(), engine.observation().numpy())
    for t in range(40):
        out = engine.step(rng_actions[:, t])
        assert torch.equal(td["next", "pixels"][:, t], engine.observation())
        assert torch.equal(td["next", "reward"][:, t, 0], out.reward.float())
        done = torch.nonzero(out.terminated | out.truncated).flatten()
        if len(done):
            engine.reset(done)
        if len(done) and t + 1 < 40:
            assert torch.equal(td["pixels"][:, t + 1][done], engine.observation()[done])


def test_stride_1_is_the_plain_stack():
    """k = 1 adds no transform and keeps S frames: the pipeline of before."""
    env = make_env({"frame_stride": 1})
    names = [type(t).__name__ for t in env.transform]
    assert "EveryKthFrame" not in names
    assert next(t for t in env.transform if type(t).__name__ == "CatFrames").N == S
    assert BatchedLaneChange({}, 2).history == S


# ----------------------------------------------------------------------- learned cars
@pytest.fixture(scope="module")
def pool(tmp_path_factory):
    from tests.helpers import save_pool

    return save_pool(tmp_path_factory.mktemp("pool"), head_scale=100.0)  # no near-ties


def _spy(controller, seen: list[np.ndarray]) -> None:
    """Record the stacks a learned-car controller feeds its networks (first car of each call)."""
    forward = controller.q_values

    def q_values(index, stacks):
        seen.append(stacks[0].cpu().numpy().copy())
        return forward(index, stacks)

    controller.q_values = q_values


def test_learned_cars_see_the_env_stride_in_both_engines(pool):
    """A learned car's network gets its own frames of steps t-3k, ..., t (the stride the agent,
    and so the network, was trained with), in the reference and the engine alike."""
    k, config = 3, {"opponent": {"type": "learned", "pool": pool}, "vehicles_count": 1, "frame_stride": 3}
    env = LaneChangeEnv(config=config)
    env.reset(seed=4)
    engine = BatchedLaneChange(config, 1)
    engine.reset(seeds=[4])
    ref_seen: list[np.ndarray] = []
    eng_seen: list[np.ndarray] = []
    _spy(env._opponents.of_kind("learned"), ref_seen)
    _spy(engine.learned, eng_seen)
    for _ in range(15):
        _, _, terminated, truncated, _ = env.step(4)
        engine.step(torch.tensor([4]))
        assert not (terminated or truncated)
    assert len(ref_seen) == len(eng_seen) == 15
    newest = [s[-1] for s in ref_seen]
    assert len({f.tobytes() for f in newest}) == 15  # the car's view changes every step
    for t, (ref, eng) in enumerate(zip(ref_seen, eng_seen, strict=True)):
        assert np.array_equal(ref, _expected(newest, t, k)) and np.array_equal(eng, ref), t


def test_learned_cars_act_alike_in_both_engines_at_stride_3(pool):
    """Learned and constant cars among crashes and auto-resets (short: a forward pass per env
    and step on the reference side)."""
    config = {"opponent": {"type": "mixed", "pool": pool, "epsilon": 0.1}, "vehicles_count": 4,
              "frame_stride": 3, "frame_stack": S}
    tally = compare(config, list(range(4, 7)), 30, random_actions(1.0), auto_reset=True)
    assert tally.resets > 0


def test_evaluation_runners_and_deploy_baseline_agree_at_stride_3():
    """The gym-env runner (FrameStack at the env's stride), the engine runner and the deploy
    baseline's simulator episodes give the same episodes of a greedy Q-network at k = 3."""
    from memrl.control.baseline import simulator_episode
    from memrl.evaluation.policies import GreedyActor
    from memrl.evaluation.runner import Job, run_jobs
    from memrl.modules.policy import GreedyPolicy
    from tests.test_engine_runner import qnet

    net = qnet(0)  # acts on what it sees: these episodes end otherwise at stride 1
    env_cfg = {"duration": 40, "vehicles_count": [0, 4], "initial_lane": "non_goal", "frame_stride": 3}
    seeds = [11, 12, 13, 14]
    jobs = [Job(env_cfg, "non_goal", list(enumerate(seeds)))]
    gym_records = run_jobs(GreedyActor(net), jobs, engine=False).records
    assert run_jobs(GreedyActor(net), jobs, engine=True).records == gym_records
    consecutive = [Job({**env_cfg, "frame_stride": 1}, "non_goal", list(enumerate(seeds)))]
    assert run_jobs(GreedyActor(net), consecutive, engine=True).records != gym_records
    env = LaneChangeEnv(config=env_cfg)
    runs = [simulator_episode(env, GreedyPolicy(net), s) for s in seeds]
    assert [(r["collided"], r["reached_target"]) for r in runs] == \
        [(r.collided, r.reached_target) for r in gym_records]
