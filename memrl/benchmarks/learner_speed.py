"""Learner updates/s: memrl's training step versus a bare PyTorch double-DQN loop.

Both do the same update on the same Table I network: online Q(s, a), the online argmax at
s', the target network's value there, eq. (1)'s 1/2 squared TD error, backward, gradient
clipping at ``agent.grad_clip``, Adam. The bare loop reuses one batch of random tensors; memrl's
step is the training loop's (``Trainer._learn``): a uniform sample from the real replay buffer
(frame-ring storage, filled with env-shaped transitions) and ``Learner.update`` (TorchRL
``DQNLoss``, ``HardUpdate``).

Variants, timed in interleaved rounds in one process (each figure is the median of its
rounds; every round's figure is kept):

- ``bare_naive``: eager, float32, NCHW, torch's default thread count, Table I's literal
  ReLU-then-pool order;
- ``bare_tuned``: the bare loop with memrl's default learner options (``agent.threads``,
  ``agent.channels_last``, ``agent.compile``, ``agent.pool_first``, ``agent.precision``);
- ``memrl_naive``: memrl with those options off (threads: torch's default);
- ``memrl_tuned``: memrl with its defaults, the training configuration;
- with ``ablation``, at the first batch size: memrl with each option flipped from its default,
  and with the whole gradient step compiled (``agent.update_mode=compiled``; its compile time
  is in ``warmup_s``);
- with ``learning``, at the first batch size: memrl with each learning option of
  :data:`LEARNING_OPTIONS` on (its cost per update beside ``memrl_tuned``, the default).
"""

from __future__ import annotations

import copy
import os
import statistics
import time
from collections.abc import Callable
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

import memrl
from memrl.dqn.config import AgentConfig

CONF_DIR = memrl.CONF_DIR
OPTIONS = ("threads", "channels_last", "compile", "pool_first", "precision")
"""The learner speed options of ``agent`` (``conf/agent/dqn.yaml``)."""
LEARNING_OPTIONS: dict[str, dict[str, Any]] = {
    "augment_shift_4": {"agent": {"augment_shift": 4}},
    "advantage_learning": {"agent": {"advantage_learning": 0.9}},
    "dueling": {"network": {"_target_": "memrl.modules.qnet.DuelingQNetwork"}},
    "layernorm": {"network": {"layernorm": True}},
    "layernorm_convs": {"network": {"layernorm": True, "layernorm_convs": True}},
    "stage1_margin": {"stage1": True},
    "c51": {"network": {"_target_": "memrl.modules.categorical.CategoricalQNetwork", "atoms": 51,
                        "v_min": None, "v_max": None}},
    "hlgauss": {"network": {"_target_": "memrl.modules.hlgauss.HLGaussQNetwork", "atoms": 51,
                            "v_min": None, "v_max": None, "sigma": 0.75}},
    "risk": {"network": {"_target_": "memrl.modules.risk.RiskQNetwork",
                         "base": {"_target_": "memrl.modules.qnet.QNetwork"}}},
}
"""Learning options timed beside the default (``learning=true``): name -> ``agent`` values,
``network`` values (over Table I's), or ``stage1``: mode B's stage-1 update (every row a demo,
DQfD's margin term at ``mode.stage1``'s default weight and margin). The value heads (``c51``,
``hlgauss``) take their support from the default task's return bounds, as training does;
``risk`` is Table I with the crash-risk critic beside it (``network=risk``)."""


def default_agent_cfg() -> DictConfig:
    """The ``agent`` node training uses: the schema with ``conf/agent/dqn.yaml`` on top."""
    cfg = OmegaConf.structured(AgentConfig)
    path = CONF_DIR / "agent" / "dqn.yaml"
    if path.exists():
        values = OmegaConf.to_container(OmegaConf.load(path))
        assert isinstance(values, dict)
        values.pop("defaults", None)
        cfg = OmegaConf.merge(cfg, values)
    return cfg  # type: ignore[return-value]


def agent_variant(base: DictConfig, **options: Any) -> DictConfig:
    cfg = copy.deepcopy(base)
    for key, value in options.items():
        cfg[key] = value
    return cfg


DEFAULT_THREADS = os.cpu_count() or 1
"""The naive thread count: one per CPU, torch's default here (``agent.threads: 0``)."""


def _threads(n: int) -> int:
    """``agent.threads`` as a count (0: torch's default)."""
    return n if n > 0 else DEFAULT_THREADS


def random_batch(n: int, seed: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    px = lambda: torch.randint(0, 256, (n, 4, 84, 84), dtype=torch.uint8, generator=g)  # noqa: E731
    return {"obs": px(), "next_obs": px(), "action": torch.randint(0, 9, (n,), generator=g),
            "reward": torch.randn(n, generator=g),
            "terminated": torch.rand(n, generator=g) < 0.1}


def bare_step(agent: DictConfig, batch: dict[str, torch.Tensor], seed: int) -> Callable[[], float]:
    """One double-DQN update of a plain PyTorch loop (no TorchRL), as a closure."""
    from memrl.dqn.learner import conv_dtype
    from memrl.modules.qnet import QNetwork

    torch.manual_seed(seed)
    net = QNetwork(pool_first=bool(agent.pool_first))
    net.conv_dtype = conv_dtype(str(agent.precision))
    if agent.channels_last:
        net = net.to(memory_format=torch.channels_last)  # type: ignore[call-overload]
    target = copy.deepcopy(net)
    if agent.compile:
        net.compile(dynamic=False)
        target.compile(dynamic=False)
    opt = torch.optim.Adam(net.parameters(), lr=float(agent.lr))
    gamma, clip = float(agent.gamma), float(agent.grad_clip)
    obs, nxt, a = batch["obs"], batch["next_obs"], batch["action"][:, None]
    r, not_term = batch["reward"], (~batch["terminated"]).float()

    def step() -> float:
        return float(bare_update(net, target, opt, (obs, nxt, a, r, not_term), gamma, clip))

    return step


def bare_update(net: torch.nn.Module, target: torch.nn.Module, opt: torch.optim.Optimizer,
                batch: tuple[torch.Tensor, ...], gamma: float, clip: float) -> torch.Tensor:
    """One plain double-DQN update of ``net`` on ``batch`` = (obs, next obs, actions ``[B, 1]``,
    rewards, not-terminated as float); returns the loss, detached."""
    obs, nxt, a, r, not_term = batch
    q = net(obs).gather(1, a).squeeze(1)
    with torch.no_grad():
        a_star = net(nxt).argmax(1, keepdim=True)
        y = r + gamma * not_term * target(nxt).gather(1, a_star).squeeze(1)
    loss = 0.5 * (q - y).pow(2).mean()
    opt.zero_grad(set_to_none=True)
    loss.backward()
    if clip > 0:
        torch.nn.utils.clip_grad_norm_(net.parameters(), clip)
    opt.step()
    return loss.detach()


def memrl_step(agent: DictConfig, buffer: Any, seed: int, network: dict[str, Any] | None = None,
               stage1: bool = False) -> Callable[[], float]:
    """The training loop's update: sample from the replay buffer, ``Learner.update`` (``network``:
    the architecture; ``stage1``: every sampled row a demo, with the margin term)."""
    from memrl.dqn.learner import Learner
    from memrl.losses import MarginTerm, td_term
    from memrl.modes import Stage1Config
    from memrl.modules.qnet import TABLE1

    torch.manual_seed(seed)
    s1 = Stage1Config()  # the margin term of mode B's stage 1 at its defaults
    terms = (td_term(agent), MarginTerm(s1.margin_weight, s1.margin)) if stage1 else None  # Table I's
    from memrl.envs.config import LaneChangeConfig
    from memrl.modules.qnet import network_for_task

    arch = network_for_task({**TABLE1, **(network or {})}, OmegaConf.structured(LaneChangeConfig),
                            float(agent.gamma))
    learner = Learner(agent, terms=terms, network=arch)
    batch_size = int(agent.batch_size)

    def step() -> float:
        batch = buffer.sample(batch_size)
        if stage1:  # the same rows, marked as demos (stage 1 samples only prior knowledge)
            batch["is_demo"] = torch.ones(batch.shape, dtype=torch.bool)
        return learner.update(batch)

    return step


def fill_buffer(transitions: int, batch_size: int, seed: int) -> Any:
    """The training buffer (``agent_buffer``, compact) holding env-shaped transitions."""
    from memrl.benchmarks.synthetic import episodes
    from memrl.data.buffers import agent_buffer

    rb = agent_buffer(transitions, batch_size)
    for ep in episodes(transitions, seed):
        rb.extend(ep)
    return rb


def _window(step: Callable[[], float], seconds: float) -> tuple[float, int]:
    """Updates/s over at least ``seconds`` (and at least one update)."""
    n, start = 0, time.perf_counter()
    while True:
        step()
        n += 1
        elapsed = time.perf_counter() - start
        if elapsed >= seconds:
            return n / elapsed, n


def _ablation(tuned: DictConfig, tuned_b: DictConfig) -> dict[str, tuple[DictConfig, str]]:
    """memrl with each speed option flipped from its default, and the other update modes."""
    specs: dict[str, tuple[DictConfig, str]] = {}
    specs[f"memrl_threads_{1 if _threads(tuned.threads) != 1 else 2}"] = (
        agent_variant(tuned_b, threads=1 if _threads(tuned.threads) != 1 else 2), "memrl")
    specs[f"memrl_channels_last_{not tuned.channels_last}".lower()] = (
        agent_variant(tuned_b, channels_last=not tuned.channels_last), "memrl")
    specs[f"memrl_compile_{not tuned.compile}".lower()] = (
        agent_variant(tuned_b, compile=not tuned.compile), "memrl")
    for mode in ("eager", "compiled"):  # the whole gradient step (agent.update_mode)
        if mode != str(tuned.update_mode):
            specs[f"memrl_update_mode_{mode}"] = (agent_variant(tuned_b, update_mode=mode), "memrl")
    flipped = "float32" if str(tuned.precision) != "float32" else "bfloat16"
    specs[f"memrl_precision_{flipped}"] = (agent_variant(tuned_b, precision=flipped), "memrl")
    return specs


def run(batch_sizes: list[int] | None = None, seconds: float = 2.0, rounds: int = 3,
        warmup_updates: int = 2, buffer_transitions: int = 5000, ablation: bool = True,
        seed: int = 0, learning: bool = True) -> dict[str, Any]:
    """Measure every variant at every batch size; returns figures and ratios."""
    batch_sizes = list(batch_sizes or [32, 128])
    tuned = default_agent_cfg()
    naive = agent_variant(tuned, threads=0, channels_last=False, compile=False, pool_first=False,
                          precision="float32")
    res: dict[str, Any] = {
        "seconds_per_window": seconds, "rounds": rounds,
        "default_options": {k: tuned[k] for k in OPTIONS},
        "torch_default_threads": DEFAULT_THREADS,
        "replay_transitions": buffer_transitions,
    }
    rb = fill_buffer(buffer_transitions, batch_sizes[0], seed)
    for b_i, batch_size in enumerate(batch_sizes):
        tuned_b = agent_variant(tuned, batch_size=batch_size)
        naive_b = agent_variant(naive, batch_size=batch_size)
        data = random_batch(batch_size, seed)
        specs: dict[str, tuple[DictConfig, str]] = {
            "bare_naive": (naive_b, "bare"), "bare_tuned": (tuned_b, "bare"),
            "memrl_naive": (naive_b, "memrl"), "memrl_tuned": (tuned_b, "memrl"),
        }
        if ablation and b_i == 0:
            specs.update(_ablation(tuned, tuned_b))
        options: dict[str, dict[str, Any]] = {}
        if learning and b_i == 0:
            for name, values in LEARNING_OPTIONS.items():
                specs[f"memrl_{name}"] = (agent_variant(tuned_b, **values.get("agent", {})), "memrl")
                options[f"memrl_{name}"] = values
        steps: dict[str, Callable[[], float]] = {}
        figures: dict[str, dict[str, Any]] = {}
        for name, (agent, kind) in specs.items():
            torch.set_num_threads(_threads(int(agent.threads)))
            start = time.perf_counter()
            extra = options.get(name, {})
            steps[name] = (bare_step(agent, data, seed) if kind == "bare" else
                           memrl_step(agent, rb, seed, extra.get("network"), bool(extra.get("stage1"))))
            for _ in range(warmup_updates):  # first calls allocate (and compile, if asked)
                steps[name]()
            figures[name] = {"threads": _threads(int(agent.threads)),
                             "channels_last": bool(agent.channels_last),
                             "compile": bool(agent.compile),
                             "update_mode": str(agent.update_mode),
                             "precision": str(agent.precision),
                             "warmup_s": round(time.perf_counter() - start, 2), "rounds": []}
        for _ in range(rounds):
            for name, step in steps.items():
                torch.set_num_threads(figures[name]["threads"])
                per_s, _n = _window(step, seconds)
                figures[name]["rounds"].append(round(per_s, 3))
        for fig in figures.values():
            fig["updates_per_s"] = round(statistics.median(fig["rounds"]), 3)
        rate = {k: v["updates_per_s"] for k, v in figures.items()}
        out: dict[str, Any] = dict(figures)
        for a, b in (("memrl_tuned", "bare_tuned"), ("memrl_naive", "bare_naive"),
                     ("memrl_tuned", "bare_naive"), ("bare_tuned", "bare_naive")):
            out[f"ratio_{a}_to_{b}"] = round(rate[a] / rate[b], 3)
        for name in options:  # each learning option's speed relative to the default
            out[f"ratio_{name}_to_memrl_tuned"] = round(rate[name] / rate["memrl_tuned"], 3)
        res[f"batch_{batch_size}"] = out
    torch.set_num_threads(DEFAULT_THREADS)
    return res
