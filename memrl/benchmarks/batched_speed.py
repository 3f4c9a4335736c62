"""Env steps/s of the batched engine at several N, beside the reference gym env and
highway-env's ``highway-fast-v0`` (gray 84x84x4), measured in the same run.

Every env runs uniformly random actions from a seeded generator and resets finished
episodes (the batched engine inside its step, ``step(auto_reset=True)``, which also returns the
finished episodes' last observations; at N=256 also with a separate ``reset()`` call); the
batched engine renders every frame (the agent's, and each learned car's own view) into its
frame ring. With ``path_time > 0`` the constant-traffic rows are timed again with every car's
path drawn (``env.bev.path_time``, ``path_length`` 0), beside them in the same run. At
``vec_sizes`` the gymnasium face is timed too: ``gym.make_vec`` (``frame_stack`` 4, numpy
observations, its next-step autoreset) on the training config's frames (every car's path
drawn at ``path_time``) beside the reference gym env on the same frames, with constant cars and
(``learned``) with learned cars. Rates are env steps per second of wall time; the JSON records
the device and the torch thread count.
"""

from __future__ import annotations

import os
import tempfile
import time
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from memrl.benchmarks.env_speed import _time_gym, highway_fast_config


def _time_batched(config: dict[str, Any], n: int, seconds: float, device: torch.device, seed: int,
                  auto_reset: bool = True) -> float:
    """Env steps/s of the batched engine with N envs, random actions, finished envs reset:
    inside the step (``auto_reset``, the last and first frames drawn in one call) or by a
    :meth:`reset` call after it."""
    from memrl.envs.batched import BatchedLaneChange

    engine = BatchedLaneChange(config, n, device)
    engine.reset(seeds=[seed + i for i in range(n)])
    gen = torch.Generator(device=device).manual_seed(seed)

    def step() -> None:
        out = engine.step(torch.randint(0, 9, (n,), generator=gen, device=device), auto_reset=auto_reset)
        if not auto_reset:
            done = torch.nonzero(out.terminated | out.truncated).flatten()
            if len(done):
                engine.reset(done)

    for _ in range(3):  # warm-up: allocations, caches
        step()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    steps, start = 0, time.perf_counter()
    while True:
        step()
        steps += 1
        if steps % 5 == 0:
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            if time.perf_counter() - start >= seconds:
                break
    return n * steps / (time.perf_counter() - start)


def _time_vec(config: dict[str, Any], n: int, seconds: float, device: torch.device, seed: int) -> float:
    """Env steps/s of ``gym.make_vec`` with N envs (4 stacked frames), random actions."""
    from memrl.envs import ENV_ID, register_envs

    register_envs()
    vec = gym.make_vec(ENV_ID, num_envs=n, vectorization_mode="vector_entry_point",
                       config={**config, "frame_stack": 4}, device=str(device))
    rng = np.random.default_rng(seed)
    vec.reset(seed=seed)
    for _ in range(3):  # warm-up: allocations, caches
        vec.step(rng.integers(9, size=n))
    steps, start = 0, time.perf_counter()
    while True:
        vec.step(rng.integers(9, size=n))
        steps += 1
        if steps % 5 == 0 and time.perf_counter() - start >= seconds:
            break
    rate = n * steps / (time.perf_counter() - start)
    vec.close()
    return rate


def _reference(config: dict[str, Any], steps: int, seed: int) -> float:
    """The reference gym env, giving 4 stacked frames as the batched engine keeps them."""
    from memrl.envs import ENV_ID, register_envs

    register_envs()
    env = gym.wrappers.FrameStackObservation(
        gym.wrappers.ReshapeObservation(gym.make(ENV_ID, config=config), (84, 84)), 4)
    rate, _ = _time_gym(env, steps, seed)
    env.close()
    return rate


def run(sizes: list[int], gpu_sizes: list[int], seconds: float = 3.0, reference_steps: int = 1000,
        vehicles_count: int = 5, learned: bool = True, learned_sizes: list[int] | None = None,
        threads: int = 1, device: str = "auto", seed: int = 0, path_time: float = 0.0,
        vec_sizes: list[int] | None = None) -> dict[str, Any]:
    """Steps/s of each layer; ratios of the batched engine to the reference gym env (and, with
    ``path_time``, of the engine drawing every car's path to the same engine without it; at
    ``vec_sizes``, of ``gym.make_vec`` to the reference gym env on the same frames)."""
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        return _run(sizes, gpu_sizes, seconds, reference_steps, vehicles_count, learned, learned_sizes,
                    device, seed, path_time, list(vec_sizes or []))
    finally:
        torch.set_num_threads(before)


def _run(sizes: list[int], gpu_sizes: list[int], seconds: float, reference_steps: int, vehicles_count: int,
         learned: bool, learned_sizes: list[int] | None, device: str, seed: int,
         path_time: float = 0.0, vec_sizes: list[int] | None = None) -> dict[str, Any]:
    from memrl.envs.batched import resolve_device

    dev = resolve_device(device)
    os.environ["SDL_VIDEODRIVER"] = "offscreen"  # 'dummy' makes highway-env skip drawing
    import highway_env  # noqa: F401  (registers highway-fast-v0)

    res: dict[str, Any] = {"device": str(dev), "device_name": torch.cuda.get_device_name(dev)
                           if dev.type == "cuda" else "cpu", "torch_threads": torch.get_num_threads(),
                           "vehicles_count": vehicles_count, "seconds_per_size": seconds}
    constant = {"vehicles_count": vehicles_count}
    hw = gym.make("highway-fast-v0", config=highway_fast_config(vehicles_count))
    res["highway_fast_gym_steps_per_s"], _ = _time_gym(hw, reference_steps, seed)
    hw.close()
    ref = _reference(constant, reference_steps, seed)
    res["reference_gym_steps_per_s"] = ref
    all_sizes = list(sizes) + (list(gpu_sizes) if dev.type == "cuda" else [])
    res["constant"] = {str(n): _time_batched(constant, n, seconds, dev, seed) for n in all_sizes}
    res["constant_ratio_to_reference"] = {n: r / ref for n, r in res["constant"].items()}
    res["reset"] = ("finished envs reset inside the step (step(auto_reset=True): their last and first "
                    "frames drawn in one call); constant_reset_after_step: reset() called after step()")
    if path_time > 0:  # every car's path drawn (bev.path_time), the same sizes and traffic
        paths = {**constant, "bev": {"path_length": 0.0, "path_time": path_time}}
        res["path_time"] = {str(n): _time_batched(paths, n, seconds, dev, seed) for n in all_sizes}
        res["path_time_ratio_to_constant"] = {n: r / res["constant"][n] for n, r in res["path_time"].items()}
    if 256 in all_sizes:  # the same loop with a separate reset call, for comparison
        rate = _time_batched(constant, 256, seconds, dev, seed, auto_reset=False)
        res["constant_reset_after_step"] = {"256": rate}
        res["constant_reset_after_step_ratio_to_reference"] = {"256": rate / ref}
    # the gymnasium face on the training config's frames, beside the reference on the same frames
    frames = {**constant, "bev": {"path_length": 0.0, "path_time": path_time}}
    if vec_sizes:
        res["vec_frames"] = f"bev.path_time={path_time}, frame_stack=4"
        ref_frames = _reference(frames, reference_steps, seed)
        res["reference_vec_frames_gym_steps_per_s"] = ref_frames
        res["make_vec"] = {str(n): _time_vec(frames, n, seconds, dev, seed) for n in vec_sizes}
        res["make_vec_ratio_to_reference"] = {n: r / ref_frames for n, r in res["make_vec"].items()}
    if learned:
        from memrl.checkpoint import save_qnet
        from memrl.modules.qnet import QNetwork

        with tempfile.TemporaryDirectory() as tmp:
            torch.manual_seed(seed)
            pool = str(save_qnet(f"{tmp}/final.pt", QNetwork(), {}))
            cars = {**constant, "opponent": {"type": "learned", "pool": [pool]}}
            ref_learned = _reference(cars, max(100, reference_steps // 5), seed)
            res["reference_learned_gym_steps_per_s"] = ref_learned
            res["learned"] = {str(n): _time_batched(cars, n, seconds, dev, seed)
                              for n in (learned_sizes or sizes)}
            res["learned_ratio_to_reference"] = {n: r / ref_learned for n, r in res["learned"].items()}
            if vec_sizes:  # learned cars on the training frames (their network saved for them)
                pool = str(save_qnet(f"{tmp}/frames/final.pt", QNetwork(), {"bev": frames["bev"]}))
                cars = {**frames, "opponent": {"type": "learned", "pool": [pool]}}
                ref_vec = _reference(cars, max(100, reference_steps // 5), seed)
                res["reference_learned_vec_frames_gym_steps_per_s"] = ref_vec
                res["make_vec_learned"] = {str(n): _time_vec(cars, n, seconds, dev, seed) for n in vec_sizes}
                res["make_vec_learned_ratio_to_reference"] = {
                    n: r / ref_vec for n, r in res["make_vec_learned"].items()}
    res["note"] = ("GPU rows (gpu_sizes) only on a CUDA device; none measured here" if dev.type != "cuda"
                   else "GPU rows measured on this device")
    res["numpy"] = np.__version__
    return res
