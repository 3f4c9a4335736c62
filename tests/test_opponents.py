"""Other cars driven by past agents: greedy on their own view, one batched pass, pools."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from memrl.checkpoint import save_qnet
from memrl.checkpoint.opponents import LearnedCarController, OpponentPoolError
from memrl.envs.config import EnvConfigError
from memrl.envs.lane_change import LaneChangeEnv
from memrl.envs.torchrl_env import make_env, unwrap
from memrl.envs.vehicles import ACTIONS
from memrl.modules.qnet import QNetwork
from memrl.train import train
from tests.helpers import TINY, save_pool

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def pool(tmp_path_factory):
    return save_pool(tmp_path_factory.mktemp("pool"))


def learned_env(pool, **extra) -> LaneChangeEnv:
    env = LaneChangeEnv(config={"opponent": {"type": "learned", "pool": pool}, **extra})
    env.reset(seed=0)
    return env


def controller(env: LaneChangeEnv) -> LearnedCarController:
    return next(c for c in env.controllers if c.kind == "learned")


def test_learned_car_takes_its_checkpoints_greedy_action_on_its_own_view(pool):
    env = learned_env(pool, vehicles_count=3)
    ctrl = controller(env)
    for _ in range(6):
        cars = list(env.others)
        before = [(c.speed, c.curvature) for c in cars]
        expected = []
        for car in cars:
            frame = env.observe_from(car, car.target_lane)  # its own view, itself centred
            stack = np.repeat(frame, 4, 0) if car.frames is None else np.concatenate(
                [car.frames[1:], frame])
            with torch.no_grad():
                q = ctrl.networks[car.policy_index](torch.from_numpy(stack))
            expected.append(int(q.argmax()))
        env.step(4)
        for car, (v, k), a in zip(cars, before, expected, strict=True):
            ds, dk = ACTIONS[a]
            assert car.speed == pytest.approx(min(max(v + 0.1 * ds, 0.0), 15.0))
            assert car.curvature == pytest.approx(min(max(k + 0.01 * dk, -0.05), 0.05))


def test_all_learned_cars_share_one_forward_pass_per_step(pool):
    env = learned_env(pool, vehicles_count=5)
    assert len(env.others) == 5 and all(c.kind == "learned" for c in env.others)
    ctrl = controller(env)
    calls = ctrl.forward_calls
    for _ in range(10):
        env.step(4)
    assert ctrl.forward_calls - calls == 10
    assert {c.policy_index for c in env.others} <= {0, 1}


def test_mixed_traffic_gives_the_configured_share(pool):
    env = LaneChangeEnv(config={"opponent": {"type": "mixed", "pool": pool,
                                             "learned_fraction": 0.3}, "vehicles_count": 5})
    kinds = []
    for seed in range(150):
        env.reset(seed=seed)
        kinds += [c.kind for c in env.others]
    share = kinds.count("learned") / len(kinds)
    assert abs(share - 0.3) < 0.05, share
    assert set(kinds) == {"learned", "constant"}


def test_learned_cars_are_reproducible_from_the_seed(pool):
    env = learned_env(pool)
    trace = []
    for _ in range(2):
        env.reset(seed=7)
        for _ in range(20):
            env.step(4)
        trace.append([(round(c.position[0], 9), round(c.position[1], 9)) for c in env.others])
    assert trace[0] == trace[1]


@pytest.mark.parametrize(("pool_value", "error", "match"), [
    (["/nonexistent/run"], ValueError, "nonexistent"),
    (["/nonexistent/*.pt"], OpponentPoolError, "no checkpoint matches"),
    ([], EnvConfigError, "opponent.pool"),
])
def test_a_bad_pool_fails_at_start_with_a_clear_error(pool_value, error, match):
    with pytest.raises(error, match=match):
        make_env({"opponent": {"type": "learned", "pool": pool_value}})


def test_the_env_makes_learned_cars_through_its_registry(pool, monkeypatch):
    """The env package imports nothing above it: memrl.checkpoint registers the learned cars'
    controller; without it, learned traffic is refused naming what to import."""
    from memrl.checkpoint.opponents import learned_cars
    from memrl.envs import controllers

    assert controllers.CONTROLLERS["learned"] is learned_cars
    monkeypatch.delitem(controllers.CONTROLLERS, "learned")
    with pytest.raises(EnvConfigError, match="learned cars, which memrl.checkpoint registers: import memrl"):
        learned_env(pool)


def test_the_gym_env_drives_learned_cars_once_memrl_checkpoint_is_imported(pool):
    code = ("import gymnasium, memrl.envs\n"
            f"config = {{'opponent': {{'type': 'learned', 'pool': {list(pool)!r}}}}}\n"
            "try:\n    gymnasium.make('memrl/LaneChange-v0', config=config).reset(seed=0)\n"
            "except ValueError as err:\n    print('refused:', err)\n"
            "import memrl.checkpoint\n"
            "env = gymnasium.make('memrl/LaneChange-v0', config=config)\n"
            "env.reset(seed=0)\n"
            "print('kinds:', [c.kind for c in env.unwrapped.controllers])\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert out.returncode == 0, out.stderr[-2000:]
    lines = out.stdout.splitlines()
    assert lines[0].startswith("refused: env config 'opponent.type': learned traffic needs the controller "
                               "of learned cars") and lines[1] == "kinds: ['learned']"


def test_a_corrupt_checkpoint_in_the_pool_is_named(tmp_path):
    bad = tmp_path / "final.pt"
    bad.write_bytes(b"garbage")
    with pytest.raises(ValueError, match="final.pt"):
        make_env({"opponent": {"type": "mixed", "pool": [str(bad)]}})


def test_opponent_group_composes_and_self_play_grows_the_pool(compose_cfg, tmp_path, pool):
    cfg = compose_cfg("train", TINY + ["opponent=mixed", f"env.opponent.pool=[{pool[0]}]",
                                       "self_play_every=1", "total_episodes=2"])
    assert cfg.env.opponent.type == "mixed"
    summary = train(cfg, tmp_path)
    assert summary.episodes == 2
    assert sorted(p.name for p in (tmp_path / "pool").iterdir()) == [
        "episode_0000001.pt", "episode_0000002.pt"]
    with pytest.raises(ValueError, match="self_play_every"):
        train(compose_cfg("train", TINY + ["self_play_every=1"]), tmp_path / "x")


def test_pool_accepts_run_folders_and_globs(pool, tmp_path):
    folder = str(tmp_path)
    save_qnet(tmp_path / "checkpoints" / "final.pt", QNetwork(), {})
    env = make_env({"opponent": {"type": "learned", "pool": [folder, pool[0].replace("agent1", "agent*")]}})
    ctrl = next(c for c in unwrap(env).controllers if c.kind == "learned")
    assert len(ctrl.networks) == 3


def test_a_pool_agent_trained_on_other_frames_is_refused_in_both_engines(tmp_path):
    """Learned cars see their views drawn with the env's BEV and stride: an agent trained on
    other frames (here: without the drawn paths, or at another stride) is refused naming the
    file and the key; agents of the same frames, and hand-saved ones without a config, drive."""
    from memrl.envs.batched import BatchedLaneChange

    plain = save_qnet(tmp_path / "plain" / "final.pt", QNetwork(), {"bev": {"path_time": 0.0}})
    paths = save_qnet(tmp_path / "paths" / "final.pt", QNetwork(), {"bev": {"path_time": 2.0}})
    strided = save_qnet(tmp_path / "strided" / "final.pt", QNetwork(),
                        {"bev": {"path_time": 2.0}, "frame_stride": 3})
    unknown = save_qnet(tmp_path / "unknown" / "final.pt", QNetwork(), {})
    here = {"bev": {"path_time": 2.0}, "vehicles_count": 3}
    for bad, text in ((plain, "bev.path_time 0.0 there, 2.0 here"),
                      (strided, "frame_stride 3 there, 1 here")):
        config = {"opponent": {"type": "learned", "pool": [str(paths), str(bad)]}, **here}
        with pytest.raises(OpponentPoolError) as info:
            LaneChangeEnv(config=config).reset(seed=0)
        message = str(info.value)
        assert str(bad) in message and text in message and "\n" not in message
        with pytest.raises(OpponentPoolError, match=text):
            BatchedLaneChange(config, num_envs=2)
    config = {"opponent": {"type": "learned", "pool": [str(paths), str(unknown)]}, **here}
    env = LaneChangeEnv(config=config)
    env.reset(seed=0)
    assert len(controller(env).networks) == 2
    assert BatchedLaneChange(config, num_envs=2).learned is not None


def test_training_refuses_a_pool_of_other_frames_before_writing_anything(tmp_path, compose_cfg):
    """The config check loads each pool agent's env: memrl's defaults draw every car's path,
    so an agent of the paper's plain frames cannot drive a learned car there."""
    plain = save_qnet(tmp_path / "plain" / "final.pt", QNetwork(), {"bev": {"path_time": 0.0}})
    cfg = compose_cfg("train", TINY + ["opponent=learned", f"env.opponent.pool=[{plain}]"])
    with pytest.raises(OpponentPoolError, match="bev.path_time 0.0 there, 2.0 here"):
        train(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()
    ok = compose_cfg("train", TINY + ["opponent=learned", f"env.opponent.pool=[{plain}]",
                                      "env.bev.path_time=0"])
    assert train(ok, tmp_path / "ok").episodes >= 1
