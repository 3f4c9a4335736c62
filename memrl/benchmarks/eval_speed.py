"""Table III's evaluation (both initial lanes of the paper's protocol) of one fresh Q-network,
timed with the gym-env runner (one worker, its default batch) and with the batched-engine
runner in the same run, on the same threads; the two must give the same records.

The time inside the Q-network's forward passes is measured apart (the same samples, the same
arithmetic in both runners): what is left is the runners' own cost (envs, frames, Python).
On CPU that forward (~19 MFLOP per sample, 0.4-0.5 ms on one thread) bounds the ratio:
``ratio_bound_by_forward`` is today's time over the engine runner's forward time alone.
With ``idle_bias > 0`` the network favours keeping speed and curvature, so episodes last
about as long as a trained agent's instead of ending in a crash after a dozen steps.

``engine_runner_recorded`` is the engine runner again as the protocol evaluation of a trained
run drives it: with ``record`` (each step's Q-values, actions and rewards kept) and the
crash-sight summary made from them (:func:`memrl.evaluation.crash_sight.summarize`, timed in
``summarize_s`` and counted in its ``wall_s``); ``record_cost`` is its wall time over the plain
engine runner's.

``checkpoints=K`` (K >= 2) adds, per network bias, K fresh networks evaluated on the engine one
after the other (``alone``) and all K on one engine per lane
(:func:`~memrl.evaluation.engine_runner.run_actors_on_engine`, ``together``), recorded as a
trained run's evaluation is; ``same_records`` checks each network's records agree.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from memrl.envs.batched import resolve_device
from memrl.envs.vehicles import IDLE
from memrl.evaluation.crash_sight import summarize
from memrl.evaluation.engine_runner import run_actors_on_engine, torch_threads
from memrl.evaluation.policies import GreedyActor
from memrl.evaluation.protocol import ProtocolConfig, protocol_env, scenario_seeds
from memrl.evaluation.runner import Job, run_jobs
from memrl.modules.qnet import QNetwork


class TimedGreedyActor(GreedyActor):
    """A greedy actor that adds up the wall time of its forward passes [s].

    Args:
        net: the Q-network.
        todays_forward: on the gym path, act as the runner's actor did before the engine
            runner (the whole channels-last network on each lockstep batch), not through
            :class:`~memrl.modules.policy.GreedyPolicy` (chunks, strided-maximum pools).
    """

    def __init__(self, net: QNetwork, todays_forward: bool = False) -> None:
        super().__init__(net)
        self.todays_forward = todays_forward
        self.seconds = 0.0
        self.samples = 0

    def act_pixels(self, pixels: torch.Tensor) -> torch.Tensor:
        start = time.perf_counter()
        out = super().act_pixels(pixels)
        if out.device.type == "cuda":
            torch.cuda.synchronize(out.device)
        self.seconds += time.perf_counter() - start
        self.samples += len(pixels)
        return out

    def act_values(self, pixels: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        start = time.perf_counter()
        out = super().act_values(pixels)
        if out[0].device.type == "cuda":
            torch.cuda.synchronize(out[0].device)
        self.seconds += time.perf_counter() - start
        self.samples += len(pixels)
        return out

    def act(self, slots: Sequence[int], envs: Sequence[Any], pixels: np.ndarray) -> np.ndarray:
        start = time.perf_counter()
        if self.todays_forward:
            with torch.inference_mode():
                x = torch.from_numpy(pixels).contiguous(memory_format=torch.channels_last)
                out = self.net(x).argmax(-1).numpy()
        else:
            out = super().act(slots, envs, pixels)
        self.seconds += time.perf_counter() - start
        self.samples += len(pixels)
        return out


def fresh_qnet(seed: int, idle_bias: float = 0.0) -> QNetwork:
    """A freshly initialised Table I network; ``idle_bias`` added to the keep-going action's Q."""
    torch.manual_seed(seed)
    net = QNetwork()
    with torch.no_grad():
        net.head[-1].bias[IDLE] += idle_bias  # type: ignore[index,operator]
    return net


def _time(net: QNetwork, jobs: list[Job], engine: bool, gym_batch: int, engine_batch: int | None,
          device: torch.device, threads: int, record: bool = False) -> tuple[dict[str, Any], list[Any]]:
    actor = TimedGreedyActor(net, todays_forward=not engine)
    start = time.perf_counter()
    with torch_threads(threads):
        res = run_jobs(actor, jobs, workers=threads, batch=gym_batch, engine=engine, device=device,
                       engine_batch=engine_batch, record=record)
        extra = {}
        if record:
            before = time.perf_counter()
            summarize(res.traces, 0.95, int(jobs[0].env["duration"]))
            extra = {"summarize_s": time.perf_counter() - before, "traces": len(res.traces)}
    wall = time.perf_counter() - start
    episodes = len(res.records)
    return {**extra, "wall_s": wall, "episodes_per_s": episodes / wall,
            "env_steps": sum(r.steps for r in res.records),
            "forward_s": actor.seconds, "forward_samples": actor.samples,
            "forward_ms_per_sample": 1e3 * actor.seconds / max(1, actor.samples),
            "without_forward_s": wall - actor.seconds}, res.records


def _one(net: QNetwork, jobs: list[Job], gym_batch: int, engine_batch: int | None, device: torch.device,
         threads: int) -> dict[str, Any]:
    today, ref = _time(net, jobs, False, gym_batch, engine_batch, torch.device("cpu"), threads)
    batched, ours = _time(net, jobs, True, gym_batch, engine_batch, device, threads)
    recorded, kept = _time(net, jobs, True, gym_batch, engine_batch, device, threads, record=True)
    return {"today_runner": today, "engine_runner": batched, "same_records": ours == ref,
            "engine_runner_recorded": recorded, "recorded_same_records": kept == ours,
            "record_cost": recorded["wall_s"] / batched["wall_s"],
            "ratio": today["wall_s"] / batched["wall_s"],
            "ratio_without_forward": today["without_forward_s"] / batched["without_forward_s"],
            # the most any runner could gain with this network: today's time over the forward alone
            "ratio_bound_by_forward": today["wall_s"] / batched["forward_s"],
            "survived": sum(r.survived for r in ours), "goal": sum(r.goal for r in ours)}


def _k_checkpoints(k: int, net_seed: int, bias: float, jobs: list[Job], device: torch.device,
                   threads: int) -> dict[str, Any]:
    """K networks evaluated one after the other, then together on one engine per lane."""
    actors = [GreedyActor(fresh_qnet(net_seed + i, bias), gamma=0.95) for i in range(k)]
    key = lambda r: (r.initial_lane, r.episode)  # noqa: E731
    with torch_threads(threads):
        start = time.perf_counter()
        alone = [run_actors_on_engine([a], jobs, device=device, threads=threads, record=True)[0]
                 for a in actors]
        mid = time.perf_counter()
        together = run_actors_on_engine(actors, jobs, device=device, threads=threads, record=True)
        end = time.perf_counter()
    same = all(sorted(a.records, key=key) == sorted(t.records, key=key)
               for a, t in zip(alone, together, strict=True))
    steps = sum(r.steps for res in together for r in res.records)
    return {"k": k, "alone_s": mid - start, "together_s": end - mid, "speedup": (mid - start) / (end - mid),
            "env_steps": steps, "together_env_steps_per_s": steps / (end - mid), "same_records": same}


def run(episodes: int = 100, duration: int = 300, vehicles_count: Sequence[int] = (0, 5), seed: int = 0,
        net_seed: int = 0, idle_bias: Sequence[float] = (0.0,), gym_batch: int = 8,
        engine_batch: int | None = None, threads: int = 1, device: str = "cpu",
        checkpoints: int = 0) -> dict[str, Any]:
    """Wall times, episodes/s and their ratio for each network (one per ``idle_bias``)."""
    dev = resolve_device(device)
    protocol = ProtocolConfig(episodes=episodes, seed=seed, vehicles_count=list(vehicles_count),
                              duration=duration)
    seeds = list(enumerate(scenario_seeds(seed, episodes)))
    jobs = [Job(protocol_env({}, protocol, lane), lane, seeds) for lane in protocol.initial_lanes]
    res: dict[str, Any] = {"device": str(dev), "threads": threads, "episodes": episodes * len(jobs),
                           "protocol": {"episodes_per_lane": episodes,
                                        "initial_lanes": protocol.initial_lanes,
                                        "vehicles_count": list(vehicles_count), "duration": duration},
                           "today_runner": f"gym envs, 1 worker, batch {gym_batch}",
                           "engine_runner": f"batched engine, {engine_batch or 'all'} envs per lane"}
    for bias in idle_bias:
        name = "fresh_qnet" if bias == 0 else f"fresh_qnet_idle_bias_{bias:g}"
        res[name] = _one(fresh_qnet(net_seed, bias), jobs, gym_batch, engine_batch, dev, threads)
        if checkpoints >= 2:
            res[name]["k_checkpoints"] = _k_checkpoints(checkpoints, net_seed, bias, jobs, dev, threads)
    return res
