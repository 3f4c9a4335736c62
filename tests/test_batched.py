"""The batched engine is the reference env's task: same scenes, steps, frames, resets; its
gymnasium and TorchRL faces; bad input; and the frame change of the shared rasterizer."""

from __future__ import annotations

import cv2
import gymnasium as gym
import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs

from memrl.envs import ENV_ID, batched
from memrl.envs.batched import BatchedEnvError, BatchedLaneChange, resolve_device
from memrl.envs.lane_change import LaneChangeEnv
from memrl.envs.render import PALETTE, gray_palette
from memrl.envs.scene import sample_scene
from memrl.envs.torchrl_env import make_env
from memrl.modules.scripted import ScriptedDriver
from tests.batched_helpers import car_states, compare, random_actions
from tests.helpers import save_pool

NON_GOAL = {"initial_lane": "non_goal", "vehicles_count": [0, 5]}


OFF_NOMINAL = {"initial_offset": 0.5, "initial_heading": 0.1, "initial_curvature": 0.02}


@pytest.mark.parametrize("config", [{}, NON_GOAL, {"target_lane": 1, "lanes_count": 3, "vehicles_count": 4},
                                    OFF_NOMINAL])
def test_env_i_reset_with_seed_s_starts_from_the_gym_scene_of_seed_s(config):
    seeds = list(range(100, 132))
    engine = BatchedLaneChange(config, len(seeds))
    engine.reset(seeds=seeds)
    for i, seed in enumerate(seeds):
        env = gym.make(ENV_ID, config=config).unwrapped
        env.reset(seed=seed)
        assert int(engine.target_lane[i]) == env.target_lane
        present = engine.present[i].numpy()
        assert present.sum() == 1 + len(env.others) and present[: present.sum()].all()
        assert np.array_equal(engine.state[i][engine.present[i]].numpy(), car_states(env))  # exact copies
        assert bool(engine.reached[i]) == env.reached_target


@pytest.fixture(params=["numpy", "torch"])
def backend(request, monkeypatch):
    """The engine's frames drawn by the rasterizer's numpy path (CPU, few views) or its torch
    path (many views, any device): both are checked against the reference."""
    if request.param == "torch":
        monkeypatch.setattr(batched, "NUMPY_MAX_VIEWS", 0)
    return request.param


def test_random_actions_match_the_reference_step_for_step_with_collisions_walls_and_resets(backend):
    """32 seeds x 300 steps of uniform random actions: crashes into cars and the road edges."""
    tally = compare(NON_GOAL, list(range(32)), 300, random_actions(1.0))
    assert tally.steps == 32 * 300
    assert tally.wall_hits > 0 and tally.collisions > tally.wall_hits  # both kinds of crash happened
    assert tally.resets > 32  # every env went through several auto-resets


def test_auto_reset_steps_match_the_reference(backend):
    """``step(auto_reset=True)`` resets finished envs inside the step (one render call for the
    last and the first frames): the same episodes, last frames and first frames as a reset."""
    tally = compare(NON_GOAL, list(range(300, 316)), 200, random_actions(1.0), auto_reset=True)
    assert tally.resets > 16 and tally.collisions > 0



def twin_engines(config: dict, pool, n: int) -> tuple[BatchedLaneChange, BatchedLaneChange]:
    """Two engines of ``config`` (its learned cars from ``pool``), reset to the same scenes."""
    if "opponent" in config:
        config = {**config, "opponent": {**config["opponent"], "pool": pool}}
    engines = BatchedLaneChange(config, n), BatchedLaneChange(config, n)
    for engine in engines:
        engine.reset(seeds=list(range(n)))
    return engines


@pytest.mark.parametrize("config", [NON_GOAL, {"opponent": {"type": "mixed", "pool": "POOL", "epsilon": 0.2},
                                              "vehicles_count": 3}])
def test_auto_reset_step_equals_step_then_reset(config, pool):
    """Same episodes, flags and frame stacks; ``final_observation`` is the stack a separate
    reset would have replaced."""
    n, rng = 10, np.random.default_rng(0)
    fused, split = twin_engines(config, pool, n)
    resets = 0
    for _ in range(80):
        actions = torch.as_tensor(rng.integers(9, size=n))
        a, b = fused.step(actions, auto_reset=True), split.step(actions)
        for key in ("reward", "terminated", "truncated", "collided", "reached_target"):
            assert torch.equal(getattr(a, key), getattr(b, key)), key
        assert a.components.keys() == b.components.keys()
        for name, value in a.components.items():
            assert torch.equal(value, b.components[name]), name
        done = torch.nonzero(b.terminated | b.truncated).flatten()
        if len(done):
            assert a.reset_ids is not None and torch.equal(a.reset_ids, done)
            assert torch.equal(a.final_observation, split.observation()[done])
            split.reset(done)
            resets += len(done)
        else:
            assert a.reset_ids is None and a.final_observation is None
        assert torch.equal(fused.observation(), split.observation())
        assert torch.equal(fused.state, split.state) and torch.equal(fused.steps, split.steps)
    assert resets > n


@pytest.mark.parametrize("config", [{**NON_GOAL, "bev": {"path_time": 2.0}},
                                    {"opponent": {"type": "mixed", "pool": "POOL", "epsilon": 0.2},
                                     "vehicles_count": 3}])
def test_step_with_reset_equals_step_then_reset(config, pool):
    """``step(reset=ids)`` (the vector env's next-step autoreset: those envs start anew instead,
    their first frames drawn with every other env's new frame) leaves the engine as
    ``step()`` then ``reset(ids)``: states, generators' draws, frame stacks."""
    n, rng = 10, np.random.default_rng(1)
    fused, split = twin_engines(config, pool, n)
    ended, resets = np.zeros(n, dtype=bool), 0
    for _ in range(80):
        actions = torch.as_tensor(rng.integers(9, size=n))
        ids = np.flatnonzero(ended).tolist()
        active = torch.as_tensor(~ended)
        a, b = fused.step(actions, active=active, reset=ids), split.step(actions, active=active)
        split.reset(ids)
        resets += len(ids)
        keep = torch.as_tensor(~ended)
        for key in ("reward", "terminated", "truncated", "collided", "reached_target"):
            assert torch.equal(getattr(a, key)[keep], getattr(b, key)[keep]), key
        assert torch.equal(fused.observation(), split.observation())
        assert torch.equal(fused.state, split.state) and torch.equal(fused.steps, split.steps)
        ended = (b.terminated | b.truncated).numpy() & ~ended
    assert resets > n
    with pytest.raises(BatchedEnvError, match="auto_reset or reset"):
        fused.step(actions, auto_reset=True, reset=[0])


def test_steady_driving_matches_the_reference_through_truncations():
    """16 seeds x 310 steps of 'keep speed and curvature' among 5 cars: rear-end crashes, and
    episodes that last the full 300 steps and are truncated, then reset."""
    tally = compare({}, list(range(32, 48)), 310, random_actions(0.0))
    assert tally.truncations > 0 and tally.collisions > 0


def test_scripted_driver_actions_match_the_reference():
    """The scripted driver changes lanes among 0-5 cars: 32 seeds x 300 steps."""
    drivers: dict[int, ScriptedDriver] = {}

    def act(envs, rng):
        out = []
        for i, env in enumerate(envs):
            if env.steps == 0:  # a new episode: a fresh driver
                drivers[i] = ScriptedDriver(merge_window=12.0)
                drivers[i].reset(env)
            out.append(drivers[i].act(env, None))
        return np.array(out)

    tally = compare(NON_GOAL, list(range(200, 232)), 300, act)
    assert tally.reached > 20  # lane changes happened


def test_path_cue_and_off_nominal_starts_match_the_reference(backend):
    config = {"bev": {"path_length": 20.0}, "initial_offset": 0.5, "initial_heading": 0.1,
              "initial_curvature": 0.02}
    compare(config, list(range(8)), 150, random_actions(0.3))


def test_every_cars_path_matches_the_reference(backend):
    """``bev.path_time``: every car's path (its speed as the line's length) in every frame,
    16 seeds x 300 steps among other cars, crashes and resets included."""
    config = {"bev": {"path_length": 0.0, "path_time": 2.0}, **NON_GOAL, "vehicles_count": [3, 5]}
    tally = compare(config, list(range(500, 516)), 300, random_actions(0.5))
    assert tally.steps == 16 * 300 and tally.collisions > 0 and tally.resets > 16


@pytest.fixture(scope="module")
def pool(tmp_path_factory):
    # spread Q-values: no near-ties that the batch composition could flip
    return save_pool(tmp_path_factory.mktemp("pool"), head_scale=100.0)


@pytest.mark.parametrize("kind", ["learned", "mixed"])
def test_learned_cars_act_as_the_reference_controller_does(pool, kind):
    config = {"opponent": {"type": kind, "pool": pool, "epsilon": 0.1}, "vehicles_count": 4}
    tally = compare(config, list(range(4)), 100, random_actions(0.3))
    assert tally.steps == 4 * 100
    compare(config, list(range(4, 8)), 60, random_actions(1.0), auto_reset=True)


@pytest.mark.parametrize("kind", ["learned", "mixed"])
def test_learned_cars_see_every_cars_path_as_the_reference_shows_it(pool, kind):
    """With ``bev.path_time`` the learned cars' own views show the speeds and curvatures of all
    cars as the step began (before any car's action applies), in both engines."""
    config = {"opponent": {"type": kind, "pool": pool, "epsilon": 0.1}, "vehicles_count": 4,
              "bev": {"path_time": 2.0}}
    tally = compare(config, list(range(4)), 100, random_actions(0.3))
    assert tally.steps == 4 * 100


def test_learned_cars_of_all_envs_share_one_forward_pass_per_step(pool):
    engine = BatchedLaneChange({"opponent": {"type": "learned", "pool": pool}, "vehicles_count": 3}, 8)
    engine.reset(seeds=list(range(8)))
    calls = engine.learned.forward_calls
    for _ in range(5):
        engine.step(torch.full((8,), 4))
    assert engine.learned.forward_calls - calls == 5
    assert int(engine.is_learned.sum()) == 8 * 3


def test_learned_cars_of_inactive_envs_cost_no_forward_and_change_no_active_env(pool):
    """An env not ``active`` (finished, about to be reset or idle) runs none of its learned cars
    through the pool; the active envs step exactly as when every env is active."""
    config = {"opponent": {"type": "learned", "pool": pool}, "vehicles_count": 3}
    every, some = BatchedLaneChange(config, 4), BatchedLaneChange(config, 4)
    for engine in (every, some):
        engine.reset(seeds=list(range(4)))
    seen: list[int] = []
    forward = some.learned.q_values
    some.learned.q_values = lambda index, stacks: (seen.append(len(stacks)), forward(index, stacks))[1]
    active = torch.tensor([True, False, True, False])
    for _ in range(6):
        a = every.step(torch.full((4,), 4))
        b = some.step(torch.full((4,), 4), active=active)
        assert torch.equal(a.reward[active], b.reward[active])
        assert torch.equal(a.terminated[active], b.terminated[active])
        assert torch.equal(every.observation()[active], some.observation()[active])
    assert int(some.is_learned[active].sum()) == 6
    assert seen == [6] * 6  # the learned cars of envs 0 and 2 only
    some.step(torch.full((4,), 4), active=torch.zeros(4, dtype=torch.bool))
    assert seen == [6] * 6  # no active env: no forward at all


def test_gymnasium_make_vec_equals_sync_vector_env_over_reference_envs():
    n, config = 6, NON_GOAL
    ref = gym.vector.SyncVectorEnv([lambda: LaneChangeEnv(config=config) for _ in range(n)])
    vec = gym.make_vec(ENV_ID, num_envs=n, vectorization_mode="vector_entry_point", config=config)
    assert vec.single_observation_space == ref.single_observation_space
    assert vec.observation_space == ref.observation_space and vec.action_space == ref.action_space
    o1, _ = ref.reset(seed=7)
    o2, _ = vec.reset(seed=7)
    assert np.array_equal(o1, o2)
    rng = np.random.default_rng(0)
    finished = 0
    for _ in range(250):
        actions = vec.action_space.sample() if rng.random() < 0.5 else rng.integers(9, size=n)
        a, b = ref.step(actions), vec.step(actions)
        assert b[0] in vec.observation_space
        for x, y in zip(a[:4], b[:4], strict=True):
            assert np.array_equal(x, y)
        for key in ("collided", "on_target_lane", "reached_target", "lane", "target_lane", "speed",
                    "curvature"):
            assert np.array_equal(a[4][key].astype(b[4][key].dtype), b[4][key]), key
            assert b[4][f"_{key}"].all()
        for key, value in a[4]["rewards"].items():
            assert np.array_equal(value, b[4]["rewards"][key]), key
        finished += int((a[2] | a[3]).sum())
    assert finished > n  # next-step autoresets happened


def test_gymnasium_reset_mask_resets_only_those_envs():
    vec = gym.make_vec(ENV_ID, num_envs=3, vectorization_mode="vector_entry_point")
    vec.reset(seed=0)
    for _ in range(5):
        vec.step(np.full(3, 8))
    before = vec.unwrapped.engine.steps.clone()
    vec.reset(seed=[None, 11, None], options={"reset_mask": np.array([False, True, False])})
    assert vec.unwrapped.engine.steps.tolist() == [before[0].item(), 0, before[2].item()]
    env = gym.make(ENV_ID).unwrapped
    env.reset(seed=11)
    engine = vec.unwrapped.engine
    assert np.array_equal(engine.state[1][engine.present[1]].numpy(), car_states(env))


def test_torchrl_batched_env_passes_check_env_specs_and_resets_done_envs():
    env = make_env(NON_GOAL, num_envs=5, seed=3)
    check_env_specs(env)
    env.set_seed(3)
    td = env.rollout(120, break_when_any_done=False)
    assert td["pixels"].shape == (5, 120, 4, 84, 84) and td["pixels"].dtype == torch.uint8
    for key in ("collided", "on_target_lane", "reached_target"):
        assert td["next", key].shape == (5, 120) and td["next", key].dtype == torch.bool
    done = td["next", "done"].squeeze(-1)
    assert done.any()  # random actions crash: these envs were reset mid-rollout
    e, t = torch.nonzero(done)[0].tolist()
    assert td["step_count"][e, t + 1].item() == 0 and td["episode_reward"][e, t + 1].item() == 0
    # the first reset of env i is the scene of seed 3 + i: its first frame is that env's
    ref = gym.make(ENV_ID, config=NON_GOAL).unwrapped
    obs, _ = ref.reset(seed=3 + 2)
    assert np.array_equal(td["pixels"][2, 0, -1].numpy(), obs[0])
    assert (td["pixels"][2, 0] == td["pixels"][2, 0, :1]).all()  # CatFrames-style padding at reset


@pytest.mark.parametrize(("action", "match"), [
    ([0, 9], "action 9 is outside the valid range 0..8"),
    ([-1, 2], "action -1 is outside"),
    ([0.0, 1.0], "must be integers in 0..8"),
    ([True, False], "must be integers"),
    ([1, 2, 3], r"must have shape \(2,\)"),
    (3, r"must have shape \(2,\)"),
])
def test_bad_action_batches_get_one_clear_error(action, match):
    engine = BatchedLaneChange({}, 2)
    engine.reset(seeds=[0, 1])
    with pytest.raises(BatchedEnvError, match=match):
        engine.step(action)


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"num_envs": 0}, "num_envs must be an int >= 1"),
    ({"num_envs": 2.5}, "num_envs must be an int >= 1"),
    ({"device": "tpu"}, "expected auto, cpu, cuda or cuda:K|not a torch device"),
    ({"device": "banana"}, "not a torch device"),
    ({"config": {"bev": {"grayscale": False}}}, "grayscale"),
])
def test_bad_engine_arguments_get_one_clear_error(kwargs, match):
    with pytest.raises(BatchedEnvError, match=match):
        BatchedLaneChange(**{"num_envs": 1, **kwargs})


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message on machines without CUDA")
def test_cuda_without_cuda_is_refused_with_a_clear_message():
    with pytest.raises(BatchedEnvError, match="CUDA is not available"):
        resolve_device("cuda")
    assert resolve_device("auto") == torch.device("cpu")


def _cv2_cars(img: np.ndarray, env: LaneChangeEnv) -> None:
    """Today's frames before the shared rasterizer: cars filled by OpenCV (for comparison)."""
    bev, g = env.bev, gray_palette(PALETTE)
    for car in env.road.vehicles:
        poly = bev.to_pixels(env.vehicle.position, bev.car_corners([car]))[0]
        inward = 0.5 * np.sign(poly - poly.mean(axis=0))
        pts = np.round((poly - 0.5 - inward) * 16).astype(np.int32)
        kind = "agent" if car is env.vehicle else car.kind
        cv2.fillConvexPoly(img, pts, g[kind], lineType=cv2.LINE_8, shift=4)


def test_shared_rasterizer_changes_todays_frames_only_on_car_outlines():
    """The reference env now draws with the batched renderer (pixel-centre coverage) instead
    of OpenCV's polygon fill: road and markings are unchanged; cars differ from the OpenCV
    drawing only in pixels on their outlines."""
    g = gray_palette(PALETTE)
    car_levels = [g["constant"], g["agent"]]
    env = LaneChangeEnv(config={"vehicles_count": 5})
    changed = total = 0
    rng = np.random.default_rng(0)
    for seed in range(12):
        env.reset(seed=seed)
        for _ in range(40):
            obs = env.step(int(rng.integers(9)) if rng.random() < 0.3 else 4)[0][0]
            if env.vehicle.crashed:
                break
            # the road alone, as drawn now, then the cars as OpenCV filled them before
            old = env.bev.render(env.vehicle.position, [], env.target_lane)
            background = ~np.isin(obs, car_levels)
            _cv2_cars(old, env)
            diff = old != obs
            car_now, car_before = ~background, np.isin(old, car_levels)
            # every changed pixel borders a pixel of another shade in one of the drawings (an
            # outline; a car that only grazes a pixel centre at the picture's edge shows in one)
            def outline(img):
                padded = np.pad(img, 1, mode="edge")
                return np.any([padded[1 + dr: 85 + dr, 1 + dc: 85 + dc] != img
                               for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1))], axis=0)

            on_outline = outline(old) | outline(obs)
            assert (on_outline[diff]).all()
            assert diff.sum() <= 0.5 * max(car_now.sum(), car_before.sum()) + 1
            changed += int(diff.sum())
            total += int(car_before.sum())
    assert 0 < changed < 0.3 * total  # it did change, and only at the edges


def test_scene_sampler_is_the_reference_envs_draw():
    """The gym env's reset draws from sample_scene: same generator state, same scene."""
    env = gym.make(ENV_ID, config=NON_GOAL).unwrapped
    env.reset(seed=5)
    from gymnasium.utils.seeding import np_random

    scene = sample_scene(env.cfg, np_random(5)[0])
    assert np.array_equal(np.vstack([scene.agent, scene.others]), car_states(env))
    assert scene.target_lane == env.target_lane


SCENE_DIGEST = "e2eb5d7a213957a9a1cb33007a0591ee2bfa8cd2f8ff16c5061b109361c42e7f"
"""sha256 of the scenes below as the sampler drew them before its speed-ups."""


def test_scene_sampler_draws_the_same_scenes_from_the_same_seeds_as_before():
    """Seeds reproduce episodes across versions: 5 configs x 300 seeds x 3 scenes each."""
    import hashlib

    from gymnasium.utils.seeding import np_random

    from memrl.envs.config import LaneChangeConfig, _build, env_config_dict

    configs = [{}, NON_GOAL, {"target_lane": 1, "lanes_count": 3, "vehicles_count": 4},
               {**OFF_NOMINAL, "spawn_attempts": 3},
               {"vehicles_count": 8, "spawn_ahead": 30.0, "opponent": {"type": "mixed", "pool": ["x"]}}]
    digest = hashlib.sha256()
    for config in configs:
        # built unchecked: the last config asks for more cars than the window always holds
        # (refused by validate_env_config), kept to pin the sampler when cars are left out
        cfg = _build(LaneChangeConfig, {**env_config_dict(), **config}, "")
        for seed in range(300):
            rng = np_random(seed)[0]
            for _ in range(3):
                s = sample_scene(cfg, rng, 3)
                digest.update(repr((s.target_lane, s.agent.tolist(), s.others.tolist(), s.learned.tolist(),
                                    s.car_target.tolist(), s.policy.tolist())).encode())
    assert digest.hexdigest() == SCENE_DIGEST


@pytest.mark.parametrize("channels", [1, 3])
def test_numpy_and_torch_paths_of_the_rasterizer_draw_the_same_pixels(channels):
    """Random views: turned and overlapping cars, cars across the picture's edges and far off
    it, empty slots, path cues at any curvature, no target lane."""
    from memrl.envs.render import BEVRenderer, View

    renderer = BEVRenderer(View(84, 84, 0.2, 0.8), 3, 4.0, (5.0, 2.0), path_length=20.0,
                           channels=channels)
    rng = np.random.default_rng(0)
    v, c = 64, 7
    center = np.stack([rng.uniform(0, 3000, v), rng.uniform(-4, 12, v)], axis=-1)
    cars = np.stack([center[:, None, 0] + rng.uniform(-45, 45, (v, c)),
                     center[:, None, 1] + rng.uniform(-12, 12, (v, c)),
                     rng.choice([0.0, 0.05, -0.3, 1.2, np.pi / 2, 3.0], (v, c))], axis=-1)
    labels = rng.integers(-1, 7, (v, c))
    target = rng.integers(-1, 3, v)
    heading, curvature = rng.uniform(-0.5, 0.5, (v, 1)), rng.choice([0.0, 0.02, -0.05], (v, 1))
    path = np.concatenate([center, heading, curvature], axis=-1)
    a = renderer.render_batch(center, target, cars, labels, path)
    b = renderer.render_batch(*(torch.from_numpy(x) for x in (center, target, cars, labels, path)))
    assert np.array_equal(a, b.numpy())
    assert len(np.unique(a)) >= 5  # road, markings and several car shades were drawn
    # every car's path (bev.path_time): any speed, heading and curvature, absent cars
    renderer = BEVRenderer(View(84, 84, 0.2, 0.8), 3, 4.0, (5.0, 2.0), path_time=2.0, max_speed=15.0,
                           max_curvature=0.05, channels=channels)  # 8 chords per path
    paths = np.concatenate([cars[..., :2], rng.uniform(-0.5, 0.5, (v, c, 1)),
                            rng.choice([0.0, 0.02, -0.05], (v, c, 1)), rng.uniform(0, 15, (v, c, 1))],
                           axis=-1)
    a = renderer.render_batch(center, target, cars, labels, paths)
    b = renderer.render_batch(*(torch.from_numpy(x) for x in (center, target, cars, labels, paths)))
    assert np.array_equal(a, b.numpy())
