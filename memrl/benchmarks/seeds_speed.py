"""K seeds' double-DQN updates in one process: K separate updates in turn versus one update of
the K networks stacked (``torch.func.stack_module_state`` + ``functional_call`` + ``vmap``).

The design measurement of K seeds per process (issue 62 item 3), in a bare PyTorch loop (no
TorchRL, no replay: one batch of random tensors per seed, as ``bench learner``'s bare loop):
Table I networks, eq. (1)'s 1/2 squared double-DQN TD error, per-seed gradient clipping at
``grad_clip``, Adam. The stacked update clips each seed's gradient by its own norm, and Adam is
elementwise, so it is the K separate updates (their first losses are compared, ``first_loss_gap``).
Timed in interleaved rounds (the median is reported); rates are updates/s of all K seeds.
"""

from __future__ import annotations

import copy
import statistics
import time
from collections.abc import Callable
from typing import Any

import torch

from memrl.benchmarks.learner_speed import bare_update
from memrl.dqn.learner import conv_dtype
from memrl.envs.batched import resolve_device
from memrl.modules.qnet import QNetwork


def _batches(k: int, n: int, seed: int, device: torch.device) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    px = lambda: torch.randint(0, 256, (k, n, 4, 84, 84), dtype=torch.uint8, generator=g)  # noqa: E731
    out = {"obs": px(), "next": px(), "action": torch.randint(0, 9, (k, n, 1), generator=g),
           "reward": torch.randn(k, n, generator=g), "alive": (torch.rand(k, n, generator=g) > 0.1).float()}
    return {key: v.to(device) for key, v in out.items()}


def separate(nets: list[QNetwork], data: dict[str, torch.Tensor], lr: float, gamma: float,
             clip: float) -> Callable[[], torch.Tensor]:
    """K updates in turn, one network each; returns their losses ``[K]``."""
    targets = [copy.deepcopy(n) for n in nets]
    opts = [torch.optim.Adam(n.parameters(), lr=lr) for n in nets]

    def step() -> torch.Tensor:
        losses = []
        for k, (net, target, opt) in enumerate(zip(nets, targets, opts, strict=True)):
            batch = tuple(data[key][k] for key in ("obs", "next", "action", "reward", "alive"))
            losses.append(bare_update(net, target, opt, batch, gamma, clip))
        return torch.stack(losses)

    return step


def stacked(nets: list[QNetwork], data: dict[str, torch.Tensor], lr: float, gamma: float,
            clip: float) -> Callable[[], torch.Tensor]:
    """One update of the K networks stacked; returns their losses ``[K]``."""
    from torch.func import functional_call, grad_and_value, stack_module_state, vmap

    params, _ = stack_module_state([copy.deepcopy(n) for n in nets])
    params = {k: v.detach().clone() for k, v in params.items()}
    target = {k: v.clone() for k, v in params.items()}
    base = copy.deepcopy(nets[0]).to("meta")  # the architecture; the weights come from `params`
    base.conv_dtype = nets[0].conv_dtype
    opt = torch.optim.Adam(list(params.values()), lr=lr)

    def loss_of(p: dict[str, torch.Tensor], tp: dict[str, torch.Tensor], obs: torch.Tensor, nxt: torch.Tensor,
                a: torch.Tensor, r: torch.Tensor, alive: torch.Tensor) -> torch.Tensor:
        q = functional_call(base, p, (obs,)).gather(1, a).squeeze(1)
        with torch.no_grad():
            best = functional_call(base, p, (nxt,)).argmax(1, keepdim=True)
            y = r + gamma * alive * functional_call(base, tp, (nxt,)).gather(1, best).squeeze(1)
        return 0.5 * (q - y).pow(2).mean()

    grads_and_losses = vmap(grad_and_value(loss_of))

    def step() -> torch.Tensor:
        grads, losses = grads_and_losses(params, target, data["obs"], data["next"], data["action"],
                                         data["reward"], data["alive"])
        if clip > 0:  # each seed's own global norm, as clip_grad_norm_ on its network
            norm = torch.sqrt(sum(g.pow(2).flatten(1).sum(1) for g in grads.values()))
            scale = (clip / (norm + 1e-6)).clamp(max=1.0)
            grads = {k: g * scale.view(-1, *[1] * (g.dim() - 1)) for k, g in grads.items()}
        for k, p in params.items():
            p.grad = grads[k]
        opt.step()
        return losses

    step.params = params  # type: ignore[attr-defined]  # the stacked weights [K, ...], for the test
    return step


def _rate(step: Callable[[], torch.Tensor], k: int, seconds: float, device: torch.device) -> float:
    n, start = 0, time.perf_counter()
    while True:
        step()
        n += 1
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        elapsed = time.perf_counter() - start
        if elapsed >= seconds:
            return k * n / elapsed


def run(seeds: list[int] | None = None, batch_size: int = 32, seconds: float = 3.0, rounds: int = 3,
        precision: str = "auto", threads: int = 1, device: str = "auto", lr: float = 2.5e-4,
        gamma: float = 0.95, grad_clip: float = 10.0, seed: int = 0) -> dict[str, Any]:
    """Per K of ``seeds``: updates/s of K separate updates and of the stacked one, interleaved."""
    dev = resolve_device(device)
    before = torch.get_num_threads()
    if threads:
        torch.set_num_threads(int(threads))
    dtype = conv_dtype(precision) if dev.type == "cpu" or precision != "auto" else None
    res: dict[str, Any] = {"device": str(dev), "batch_size": batch_size, "precision": precision,
                           "conv_dtype": str(dtype), "threads": torch.get_num_threads()}
    for k in seeds or [1, 5]:
        torch.manual_seed(seed)
        nets = [QNetwork().to(dev) for _ in range(k)]
        for net in nets:
            net.conv_dtype = dtype
        data = _batches(k, batch_size, seed, dev)
        steps = {"separate": separate(copy.deepcopy(nets), data, lr, gamma, grad_clip),
                 "stacked": stacked(nets, data, lr, gamma, grad_clip)}
        first = {name: step() for name, step in steps.items()}  # also the first calls' allocations
        row: dict[str, Any] = {"first_loss_gap": float((first["separate"] - first["stacked"]).abs().max())}
        for name in steps:
            row[name] = []
        for _ in range(rounds):
            for name, step in steps.items():
                row[name].append(round(_rate(step, k, seconds, dev), 3))
        for name in steps:
            row[f"{name}_updates_per_s"] = statistics.median(row[name])
        row["ratio_stacked_to_separate"] = round(
            row["stacked_updates_per_s"] / row["separate_updates_per_s"], 3)
        res[f"k_{k}"] = row
    torch.set_num_threads(before)
    return res
