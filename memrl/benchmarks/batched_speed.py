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
(``learned``) with learned cars. The two rows of each of those ratios (paths / constant,
make_vec / reference) are timed side by side: built once, they take turns in ``rounds`` rounds,
so that a machine whose speed drifts moves both alike; the rows report the medians of their
rounds, the ratio the median of the rounds' ratios (each round's beside it). Rates are env
steps per second of wall time; the JSON records the device and the torch thread count.
"""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from memrl.benchmarks.env_speed import _time_gym, highway_fast_config


class _Blocks:
    """One stepper, built and warmed up once, timed in blocks of wall time (so that two of them
    can take turns: a ratio from blocks side by side, not from two stretches minutes apart)."""

    def __init__(self, step: Callable[[], None], per_step: int, device: torch.device | None = None,
                 close: Callable[[], None] = lambda: None) -> None:
        self.step, self.per_step, self.device, self.close = step, per_step, device, close
        for _ in range(3):  # warm-up: allocations, caches
            step()

    def _sync(self) -> None:
        if self.device is not None and self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    def rate(self, seconds: float) -> float:
        """Env steps/s over at least ``seconds`` of stepping (checked every 5 steps)."""
        self._sync()
        steps, start = 0, time.perf_counter()
        while True:
            self.step()
            steps += 1
            if steps % 5 == 0:
                self._sync()
                if time.perf_counter() - start >= seconds:
                    break
        return self.per_step * steps / (time.perf_counter() - start)


def _engine_blocks(config: dict[str, Any], n: int, device: torch.device, seed: int,
                   auto_reset: bool = True) -> _Blocks:
    """The batched engine with N envs, random actions, finished envs reset: inside the step
    (``auto_reset``, the last and first frames drawn in one call) or by a :meth:`reset` call
    after it."""
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

    return _Blocks(step, n, device)


def _time_batched(config: dict[str, Any], n: int, seconds: float, device: torch.device, seed: int,
                  auto_reset: bool = True) -> float:
    """Env steps/s of the batched engine with N envs over ``seconds`` (:func:`_engine_blocks`)."""
    return _engine_blocks(config, n, device, seed, auto_reset).rate(seconds)


def _vec_blocks(config: dict[str, Any], n: int, device: torch.device, seed: int) -> _Blocks:
    """``gym.make_vec`` with N envs (4 stacked frames), random actions."""
    from memrl.envs import ENV_ID, register_envs

    register_envs()
    vec = gym.make_vec(ENV_ID, num_envs=n, vectorization_mode="vector_entry_point",
                       config={**config, "frame_stack": 4}, device=str(device))
    rng = np.random.default_rng(seed)
    vec.reset(seed=seed)
    return _Blocks(lambda: vec.step(rng.integers(9, size=n)), n, close=vec.close)


def _reference_env(config: dict[str, Any]) -> gym.Env:
    """The reference gym env, giving 4 stacked frames as the batched engine keeps them."""
    from memrl.envs import ENV_ID, register_envs

    register_envs()
    return gym.wrappers.FrameStackObservation(
        gym.wrappers.ReshapeObservation(gym.make(ENV_ID, config=config), (84, 84)), 4)


def _gym_blocks(config: dict[str, Any], seed: int) -> _Blocks:
    """The reference gym env (:func:`_reference_env`), random actions, reset when done (20
    warm-up steps, as :func:`_time_gym`: first renders allocate surfaces and caches)."""
    env = _reference_env(config)
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)

    def step() -> None:
        _, _, term, trunc, _ = env.step(int(rng.integers(9)))
        if term or trunc:
            env.reset()

    for _ in range(17):  # and 3 more in _Blocks
        step()
    return _Blocks(step, 1, close=env.close)


def _side_by_side(blocks: dict[str, _Blocks], rounds: int, seconds: float) -> dict[str, list[float]]:
    """Each stepper's rate in ``rounds`` rounds, the steppers taking turns within each round,
    ``seconds / rounds`` each per round; then closed."""
    rates: dict[str, list[float]] = {name: [] for name in blocks}
    for _ in range(rounds):
        for name, b in blocks.items():
            rates[name].append(b.rate(seconds / rounds))
    for b in blocks.values():
        b.close()
    return rates


def _median(values: list[float]) -> float:
    return float(np.median(values))


def _reference(config: dict[str, Any], steps: int, seed: int) -> float:
    """Steps/s of the reference gym env (:func:`_reference_env`) over ``steps`` steps."""
    env = _reference_env(config)
    rate, _ = _time_gym(env, steps, seed)
    env.close()
    return rate


def run(sizes: list[int], gpu_sizes: list[int], seconds: float = 3.0, reference_steps: int = 1000,
        vehicles_count: int = 5, learned: bool = True, learned_sizes: list[int] | None = None,
        threads: int = 1, device: str = "auto", seed: int = 0, path_time: float = 0.0,
        vec_sizes: list[int] | None = None, rounds: int = 3) -> dict[str, Any]:
    """Steps/s of each layer; ratios of the batched engine to the reference gym env (and, with
    ``path_time``, of the engine drawing every car's path to the same engine without it; at
    ``vec_sizes``, of ``gym.make_vec`` to the reference gym env on the same frames: those two
    side by side, in ``rounds`` turns)."""
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        return _run(sizes, gpu_sizes, seconds, reference_steps, vehicles_count, learned, learned_sizes,
                    device, seed, path_time, list(vec_sizes or []), int(rounds))
    finally:
        torch.set_num_threads(before)


def _pair(res: dict[str, Any], key: str, rows: tuple[str, str], n: int, blocks: dict[str, _Blocks],
          rounds: int, seconds: float) -> None:
    """Time ``blocks`` (two steppers, ``rows`` their result keys) side by side at size ``n``,
    ``seconds`` each in all: each row's median rate, and ``key``'s ratio (first over second):
    the median of the rounds' ratios, beside them (``<key>_rounds``)."""
    rates = _side_by_side(blocks, rounds, seconds)
    first, second = (rates[name] for name in blocks)
    for row, values in zip(rows, (first, second), strict=True):
        res.setdefault(row, {})[str(n)] = _median(values)
    ratios = [x / y for x, y in zip(first, second, strict=True)]
    res.setdefault(key, {})[str(n)] = _median(ratios)
    res.setdefault(f"{key}_rounds", {})[str(n)] = ratios


def _run(sizes: list[int], gpu_sizes: list[int], seconds: float, reference_steps: int, vehicles_count: int,
         learned: bool, learned_sizes: list[int] | None, device: str, seed: int,
         path_time: float = 0.0, vec_sizes: list[int] | None = None, rounds: int = 3) -> dict[str, Any]:
    from memrl.envs.batched import resolve_device

    dev = resolve_device(device)
    os.environ["SDL_VIDEODRIVER"] = "offscreen"  # 'dummy' makes highway-env skip drawing
    import highway_env  # noqa: F401  (registers highway-fast-v0)

    res: dict[str, Any] = {"device": str(dev), "device_name": torch.cuda.get_device_name(dev)
                           if dev.type == "cuda" else "cpu", "torch_threads": torch.get_num_threads(),
                           "vehicles_count": vehicles_count, "seconds_per_size": seconds, "rounds": rounds}
    res["side_by_side"] = (f"the two rows of each ratio take turns, {rounds} rounds of seconds / {rounds} "
                           "each; their rates are the medians, the ratio the median of the rounds' ratios")
    constant = {"vehicles_count": vehicles_count}
    hw = gym.make("highway-fast-v0", config=highway_fast_config(vehicles_count))
    res["highway_fast_gym_steps_per_s"], _ = _time_gym(hw, reference_steps, seed)
    hw.close()
    ref = _reference(constant, reference_steps, seed)
    res["reference_gym_steps_per_s"] = ref
    all_sizes = list(sizes) + (list(gpu_sizes) if dev.type == "cuda" else [])
    # every car's path drawn (bev.path_time): the training config's frames
    frames = {**constant, "bev": {"path_length": 0.0, "path_time": path_time}}
    for n in all_sizes:
        if path_time > 0:  # beside the same engine without the paths, in turns
            _pair(res, "path_time_ratio_to_constant", ("path_time", "constant"), n,
                  {"path_time": _engine_blocks(frames, n, dev, seed),
                   "constant": _engine_blocks(constant, n, dev, seed)}, rounds, seconds)
        else:
            res.setdefault("constant", {})[str(n)] = _time_batched(constant, n, seconds, dev, seed)
    res["constant_ratio_to_reference"] = {n: r / ref for n, r in res["constant"].items()}
    res["reset"] = ("finished envs reset inside the step (step(auto_reset=True): their last and first "
                    "frames drawn in one call); constant_reset_after_step: reset() called after step()")
    if 256 in all_sizes:  # the same loop with a separate reset call, for comparison
        rate = _time_batched(constant, 256, seconds, dev, seed, auto_reset=False)
        res["constant_reset_after_step"] = {"256": rate}
        res["constant_reset_after_step_ratio_to_reference"] = {"256": rate / ref}
    # the gymnasium face on the training config's frames, beside the reference on the same frames
    if vec_sizes:
        res["vec_frames"] = f"bev.path_time={path_time}, frame_stack=4"
        for n in vec_sizes:
            _pair(res, "make_vec_ratio_to_reference", ("make_vec", "reference_vec_frames_gym_steps_per_s"), n,
                  {"vec": _vec_blocks(frames, n, dev, seed), "reference": _gym_blocks(frames, seed)},
                  rounds, seconds)
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
                for n in vec_sizes:
                    _pair(res, "make_vec_learned_ratio_to_reference",
                          ("make_vec_learned", "reference_learned_vec_frames_gym_steps_per_s"), n,
                          {"vec": _vec_blocks(cars, n, dev, seed), "reference": _gym_blocks(cars, seed)},
                          rounds, seconds)
    res["note"] = ("GPU rows (gpu_sizes) only on a CUDA device; none measured here" if dev.type != "cuda"
                   else "GPU rows measured on this device")
    res["numpy"] = np.__version__
    return res
