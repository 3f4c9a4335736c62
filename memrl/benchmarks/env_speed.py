"""Env steps/s: memrl's lane-change env versus highway-env's ``highway-fast-v0`` (pixels).

Both envs run random actions from a seeded generator, resetting when an episode ends, at two
layers: the gymnasium env giving ``[4, 84, 84]`` uint8 (memrl through gymnasium's
``FrameStackObservation``) and the TorchRL ``GymEnv`` pipeline that training uses (memrl's
``make_env``; highway-fast in a plain ``GymEnv``). Each pair is timed in the same process.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np


def highway_fast_config(vehicles_count: int, stack: int = 4) -> dict[str, Any]:
    """``highway-fast-v0`` with its ``GrayscaleObservation`` at 84x84 and ``stack`` frames."""
    return {
        "vehicles_count": vehicles_count,
        "observation": {
            "type": "GrayscaleObservation",
            "observation_shape": (84, 84),
            "stack_size": stack,
            "weights": [0.2989, 0.5870, 0.1140],
            "scaling": 1.75,
        },
    }


def _time_gym(env: gym.Env, steps: int, seed: int) -> tuple[float, np.ndarray]:
    rng = np.random.default_rng(seed)
    n_actions = int(env.action_space.n)  # type: ignore[attr-defined]
    obs, _ = env.reset(seed=seed)
    for _ in range(20):  # warm-up: first renders allocate surfaces and caches
        obs, _, term, trunc, _ = env.step(int(rng.integers(n_actions)))
        if term or trunc:
            obs, _ = env.reset()
    start = time.perf_counter()
    for _ in range(steps):
        obs, _, term, trunc, _ = env.step(int(rng.integers(n_actions)))
        if term or trunc:
            obs, _ = env.reset()
    return steps / (time.perf_counter() - start), np.asarray(obs)


def _time_torchrl(make: Callable[[], Any], steps: int, seed: int) -> tuple[float, np.ndarray]:
    import torch

    torch.manual_seed(seed)
    env = make()
    env.set_seed(seed)
    env.rollout(20, break_when_any_done=False)
    start = time.perf_counter()
    td = env.rollout(steps, break_when_any_done=False)
    rate = steps / (time.perf_counter() - start)
    pixels = td["pixels"][-1] if "pixels" in td.keys() else td["observation"][-1]
    env.close()
    return rate, pixels.numpy()


def _check_frame(name: str, frame: np.ndarray) -> None:
    if frame.std() == 0:
        raise RuntimeError(f"{name}: the observation is blank (constant {frame.flat[0]}): "
                           "pygame is not drawing; set SDL_VIDEODRIVER=offscreen")


def run(steps: int = 1500, vehicles_count: int = 5, seed: int = 0, torchrl: bool = True) -> dict:
    """Measure env steps/s of both envs; returns figures and same-layer ratios."""
    os.environ["SDL_VIDEODRIVER"] = "offscreen"  # 'dummy' makes highway-env skip drawing
    import highway_env  # noqa: F401  (registers highway-fast-v0)

    from memrl.envs import ENV_ID, register_envs
    from memrl.envs.torchrl_env import make_env

    register_envs()
    mem_cfg = {"vehicles_count": vehicles_count}
    hw_cfg = highway_fast_config(vehicles_count)
    res: dict[str, Any] = {"steps": steps, "vehicles_count": vehicles_count}
    # Same output as highway's GrayscaleObservation: 4 stacked 84x84 grayscale frames.
    mem = gym.wrappers.FrameStackObservation(
        gym.wrappers.ReshapeObservation(gym.make(ENV_ID, config=mem_cfg), (84, 84)), 4)
    hw = gym.make("highway-fast-v0", config=hw_cfg)
    res["memrl_gym_steps_per_s"], f1 = _time_gym(mem, steps, seed)
    res["highway_fast_gym_steps_per_s"], f2 = _time_gym(hw, steps, seed)
    _check_frame("memrl", f1)
    _check_frame("highway-fast-v0", f2)
    res["memrl_obs_shape"], res["highway_fast_obs_shape"] = list(f1.shape), list(f2.shape)
    res["ratio_gym"] = res["memrl_gym_steps_per_s"] / res["highway_fast_gym_steps_per_s"]
    mem.close()
    hw.close()
    if torchrl:
        from torchrl.envs.libs.gym import GymEnv

        res["memrl_torchrl_steps_per_s"], f3 = _time_torchrl(
            lambda: make_env(mem_cfg), steps, seed)
        res["highway_fast_torchrl_steps_per_s"], f4 = _time_torchrl(
            lambda: GymEnv("highway-fast-v0", config=hw_cfg, categorical_action_encoding=True),
            steps, seed)
        _check_frame("memrl (torchrl)", f3)
        _check_frame("highway-fast-v0 (torchrl)", f4)
        res["ratio_torchrl"] = (res["memrl_torchrl_steps_per_s"]
                                / res["highway_fast_torchrl_steps_per_s"])
    return res


def run_opponents(steps: int = 1000, vehicles_count: int = 5, seed: int = 0) -> dict:
    """TorchRL env steps/s with ``vehicles_count`` learned cars vs as many constant cars.

    The learned cars' pool is one freshly initialised Table I network (weights do not change
    the cost): each step renders every learned car's own view and runs one batched forward.
    """
    import tempfile

    import torch

    from memrl.checkpoint import save_qnet
    from memrl.envs.torchrl_env import make_env
    from memrl.modules.qnet import QNetwork

    with tempfile.TemporaryDirectory() as tmp:
        torch.manual_seed(seed)
        pool = str(save_qnet(f"{tmp}/final.pt", QNetwork(), {}))
        # Cars keep their count over the episode: no spawning, so both runs draw 5 cars.
        base = {"vehicles_count": vehicles_count}
        learned = {**base, "opponent": {"type": "learned", "pool": [pool]}}
        res: dict[str, Any] = {"steps": steps, "vehicles_count": vehicles_count,
                               "torch_threads": torch.get_num_threads()}
        res["constant_steps_per_s"], _ = _time_torchrl(lambda: make_env(base), steps, seed)
        res["learned_steps_per_s"], _ = _time_torchrl(lambda: make_env(learned), steps, seed)
    res["ratio_learned_to_constant"] = res["learned_steps_per_s"] / res["constant_steps_per_s"]
    return res
