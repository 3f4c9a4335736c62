"""The opponent pool's forward: one pass per network on its own cars (memrl's
:meth:`~memrl.checkpoint.opponents.LearnedCarController.q_values`) beside the reference, ``vmap``
over the pool's stacked networks (what memrl did before: every network on every car).

Fresh Table I networks (weights do not change the cost), random 4x84x84 stacks, each car
assigned a network at random; both variants timed in interleaved rounds (median reported),
and compared: largest Q-value difference and greedy-action agreement.
"""

from __future__ import annotations

import copy
import statistics
import time
from collections.abc import Callable
from typing import Any

import torch
from torch.func import functional_call, stack_module_state


def vmap_forward(networks: list[torch.nn.Module]) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """The reference (memrl's pool forward up to commit bffddbd): the networks stacked once,
    then per call every network on every car under ``vmap`` and car i's row of network
    ``index[i]``."""
    params, buffers = stack_module_state(networks)  # type: ignore[arg-type]
    params = {k: v.detach() for k, v in params.items()}
    skeleton = copy.deepcopy(networks[0]).to("meta")

    def run(p: dict, b: dict, x: torch.Tensor) -> torch.Tensor:
        return functional_call(skeleton, (p, b), (x,))

    def forward(index: torch.Tensor, stacks: torch.Tensor) -> torch.Tensor:
        every = torch.vmap(run, in_dims=(0, 0, None))(params, buffers, stacks)
        return every[index, torch.arange(len(index))]

    return forward


def _ms_per_call(fn: Any, seconds: float) -> float:
    start, calls = time.perf_counter(), 0
    while (elapsed := time.perf_counter() - start) < seconds or calls == 0:
        fn()
        calls += 1
    return 1000.0 * elapsed / calls


def run(cars: list[int], networks: int = 3, seconds: float = 2.0, rounds: int = 3, threads: int = 1,
        seed: int = 0) -> dict[str, Any]:
    """ms per call of both variants at each number of cars (median over ``rounds``)."""
    from memrl.checkpoint.opponents import LearnedCarController
    from memrl.modules.qnet import QNetwork

    torch.manual_seed(seed)
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        pool = LearnedCarController([QNetwork() for _ in range(networks)])
        reference = vmap_forward(pool.networks)
        res: dict[str, Any] = {"networks": networks, "threads": threads, "grouped_ms": {}, "vmap_ms": {},
                               "speedup": {}, "max_abs_q": {}, "max_abs_q_difference": {},
                               "greedy_agreement": {}}
        with torch.no_grad():
            for m in cars:
                x = torch.rand(m, 4, 84, 84)
                index = torch.randint(0, networks, (m,))
                ours, ref = pool.q_values(index, x), reference(index, x)
                res["max_abs_q"][str(m)] = float(ref.abs().max())
                res["max_abs_q_difference"][str(m)] = float((ours - ref).abs().max())
                res["greedy_agreement"][str(m)] = float((ours.argmax(-1) == ref.argmax(-1)).float().mean())
                grouped, vmapped = [], []
                for _ in range(rounds):
                    grouped.append(_ms_per_call(lambda i=index, s=x: pool.q_values(i, s), seconds))
                    vmapped.append(_ms_per_call(lambda i=index, s=x: reference(i, s), seconds))
                g, v = statistics.median(grouped), statistics.median(vmapped)
                res["grouped_ms"][str(m)], res["vmap_ms"][str(m)], res["speedup"][str(m)] = g, v, v / g
    finally:
        torch.set_num_threads(before)
    return res
