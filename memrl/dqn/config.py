"""Typed schemas of the training config groups ``agent`` and ``buffer`` (each mode's ``mode``
schema is declared with the mode, :mod:`memrl.modes`).

Registered with Hydra's ConfigStore so that a misspelt key fails at composition, and checked
by :func:`check_train_config` so that an out-of-range value fails at start, naming the key.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from omegaconf import DictConfig

from memrl.errors import config_error
from memrl.fields import check_fields, spec
from memrl.modes import mode_of

PRECISIONS = ("auto", "float32", "bfloat16")
UPDATE_MODES = ("eager", "compiled", "captured")
EXPLORATIONS = ("epsilon", "ez_greedy", "ez_speed", "speed_only", "boltzmann")  # memrl/dqn/exploration.py


@dataclass
class AgentConfig:
    """Double DQN learner (Table II where the paper fixes a value)."""

    gamma: float = spec(0.95, gt=0, le=1)
    """Discount factor (Table II)."""
    n_step: int = spec(1, ge=1)
    """Steps of reward summed per sampled transition (n-step returns, :mod:`memrl.data.nstep`):
    its reward is ``sum_{i<m} gamma^i r_{t+i}`` over up to ``n_step`` steps of its episode, the
    bootstrap ``gamma^m max Q(s_{t+m})``; a crash within the window ends the sum without a
    bootstrap. 1: the 1-step target of the paper. Applies to agent data and demos alike."""
    advantage_learning: float = spec(0.0, ge=0, lt=1)
    """Advantage learning's alpha in [0, 1) (Bellemare et al., 2016; :class:`memrl.losses.TDTerm`):
    every TD target less alpha (max_b Q_target(s, b) - Q_target(s, a)), which multiplies the
    gap between the best action and the others by 1 / (1 - alpha) (their paper: 0.9). 0: eq. (1).
    Every stage; costs one forward of the target network per update."""
    lr: float = spec(2.5e-4, gt=0)
    """Adam learning rate."""
    batch_size: int = spec(32, ge=1)
    """Transitions per update."""
    target_update_interval: int = spec(500, ge=1)
    """Updates between hard copies of the online network into the target network."""
    train_every: int = spec(4, ge=1)
    """Env steps between update rounds."""
    updates_per_round: int = spec(1, ge=1)
    """Gradient updates per round."""
    warmup_frames: int = spec(500, ge=0)
    """Env steps with random actions before the first update (agent data only)."""
    eps_start: float = spec(1.0, ge=0, le=1)
    """Initial epsilon of the linearly decaying epsilon-greedy policy (Table II)."""
    eps_end: float = spec(0.05, ge=0, le=1)
    """Final epsilon."""
    eps_decay_frames: int = spec(50_000, ge=1)
    """Env steps over which epsilon decays linearly from eps_start to eps_end."""
    exploration: str = spec("epsilon", choices=EXPLORATIONS)
    """How the acting policy explores (:mod:`memrl.dqn.exploration`): ``epsilon`` (the paper's
    epsilon-greedy), ``ez_greedy`` (a random action repeated for a zeta-distributed duration),
    ``ez_speed`` (a random speed change held so, the curvature change greedy), ``speed_only``
    (random actions change only the speed) or ``boltzmann`` (softmax over Q)."""
    ez_mu: float = spec(2.0, gt=0)
    """``ez_greedy`` / ``ez_speed``: exponent of the duration distribution P(n) ~ n^-mu."""
    ez_max_duration: int = spec(50, ge=1)
    """``ez_greedy`` / ``ez_speed``: longest repeat [action steps]."""
    temperature_start: float = spec(1.0, gt=0)
    """``boltzmann``: initial temperature [Q units], annealed like epsilon over eps_decay_frames."""
    temperature_end: float = spec(0.05, gt=0)
    """``boltzmann``: final temperature [Q units]."""
    grad_clip: float = spec(10.0, ge=0)
    """Max global gradient norm (0: no clipping)."""
    pool_first: bool = True
    """Max-pool before ReLU in the Q-network: the same outputs as Table I's ReLU-then-pool
    (ReLU is monotonic) with a quarter of the ReLU work."""
    threads: int = spec(1, ge=0)
    """torch intra-op threads (0: leave torch's default, one per core). 1 is the robust fastest
    on 2 cores (``python -m memrl.bench learner``): a second OpenMP thread makes an update about
    1.5x faster on an idle machine, but about 10x slower as soon as another process holds a
    core (a sweep job, an evaluation, other users), where 1 thread keeps its speed."""
    channels_last: bool = True
    """Q-network weights (and so activations) in channels_last (NHWC) memory format: the
    CPU conv and max-pool kernels run faster (measured by ``python -m memrl.bench learner``)."""
    compile: bool = False
    """``torch.compile`` the Q-network's forward (falls back to eager with a warning if it
    fails). Off: on this CPU it measured no faster than eager channels_last (inductor keeps the
    oneDNN convolutions), and compiling costs 10-70 s at start."""
    update_mode: str = spec("eager", choices=UPDATE_MODES)
    """How the whole gradient step runs (:class:`memrl.dqn.learner.Learner`): ``eager``;
    ``compiled``: the stage's loss terms, backward, gradient clipping and Adam as one
    ``torch.compile``d function (recompiled when a stage changes its terms or learning rate, or
    a teacher's scale changes; falls back to eager with a warning if compiling fails);
    ``captured``: the same compiled with ``mode="reduce-overhead"`` (CUDA graphs) and a
    capturable Adam, CUDA only. Sampling and the target network's hard copy stay outside."""
    loss_readback: int = spec(1, ge=1)
    """Updates between host reads of the loss values (one read of k losses at once): on a GPU,
    k > 1 keeps the update loop free of a device synchronisation per update. The logged values
    are the same for any k."""
    precision: str = spec("auto", choices=PRECISIONS)
    """Conv trunk precision: ``float32``; ``bfloat16`` (autocast of the three convs, weights,
    FC head, Q-values and loss stay float32); ``auto``: bfloat16 where the CPU has native
    bf16 (oneDNN's check, e.g. AVX512-BF16 or AMX), else float32. Measured ~2x faster updates
    at batch 32 on such a CPU (``python -m memrl.bench learner``), same loss curve."""
    augment_shift: int = spec(0, ge=0, le=20)
    """DrQ-style random shifts of each sampled stack by up to this many pixels (0: off;
    :mod:`memrl.dqn.augment`): replicate-padded, one offset per stack (its 4 frames move
    together), independent for ``pixels`` and ``next.pixels``; sampled batches only, never
    stored data or acting."""
    overlap: bool = True
    """Collect the next ``train_every`` env steps in a second thread while the learner updates
    (the batch is sampled first; the new steps join the buffer after the update). The acting
    network is a copy refreshed after every update round, so it lags one round behind the
    sequential schedule; runs stay deterministic and resume exactly. Measured by
    ``python -m memrl.bench e2e``."""

    @staticmethod
    def check(a: Any, prefix: str = "agent.") -> None:
        """Rules across its keys: schedules that decay."""
        _need(a.eps_end <= a.eps_start, f"{prefix}eps_start",
              f"need 0 <= eps_end <= eps_start <= 1, got {a.eps_start} -> {a.eps_end}")
        _need(a.temperature_end <= a.temperature_start, f"{prefix}temperature_start",
              "need 0 < temperature_end <= temperature_start")


@dataclass
class BufferConfig:
    """Replay buffer."""

    capacity: int = spec(100_000, ge=1)
    """Total transitions held (Table II: 1e5), prior knowledge included in mode A."""
    compact: bool = True
    """Store each 84x84 frame once (a frame ring; stacks rebuilt at sampling: 1.41 GB for
    1e5 transitions) instead of both full stacks per transition (5.6 GB); same samples."""
    crash_share: float = spec(0.0, ge=0, lt=1)
    """Share of the agent part of every batch drawn from the stored transitions that end in a
    crash, the rest uniform (memrl/data/crash_sampler.py); 0: uniform, as the paper."""
    priority: float = spec(0.0, ge=0, le=1)
    """Prioritized replay of the agent part (Schaul et al., 2016; memrl/data/priority_sampler.py):
    the priority exponent alpha, items drawn in proportion to ``(|TD error| + 1e-3) ** alpha``;
    0: uniform, as the paper. Excludes ``crash_share``. Dopamine's Rainbow uses 0.5."""
    priority_beta: float = spec(0.5, ge=0, le=1)
    """Importance-sampling exponent of prioritized replay (0: no correction, 1: full); fixed
    over the run, as Dopamine's Rainbow (0.5)."""

    @staticmethod
    def check(b: Any, prefix: str = "buffer.") -> None:
        """Rules across its keys: one way of choosing the agent part's items."""
        _need(b.priority == 0 or b.crash_share == 0, f"{prefix}priority",
              "prioritized replay and buffer.crash_share exclude each other; set one of them to 0")


def check_train_config(cfg: DictConfig) -> None:
    """The learner's nodes of a train config (``agent``, ``buffer``, ``mode``; ``env`` is
    checked first, by its own validator): each against its schema (:func:`check_fields`: the
    ranges on its fields, then its own cross-key ``check``), then the rules across nodes."""
    mode = mode_of(cfg)  # an unknown mode.name is refused here
    for schema, node, prefix in ((AgentConfig, cfg.agent, "agent."), (BufferConfig, cfg.buffer, "buffer."),
                                 (mode.schema, cfg.mode, "mode.")):
        check_fields(schema, node, prefix)
    check_across_nodes(cfg, max((float(st.demo_share(cfg.mode)) for st in mode.stages if not st.offline),
                                default=0.0))
    from memrl.data.buffer_size import check_buffer_fits

    check_buffer_fits(cfg)  # before anything is allocated


def check_across_nodes(cfg: DictConfig, demo_share: float) -> None:
    """The rules between the train config's nodes (``demo_share``: the most of the buffer its
    mode's online stages keep for prior knowledge)."""
    a, b = cfg.agent, cfg.buffer
    _need(a.n_step <= cfg.env.duration, "agent.n_step",
          f"{a.n_step} steps summed is longer than an episode (env.duration={cfg.env.duration})")
    _need(cfg.env.shaping.weight == 0 or cfg.env.shaping.gamma == a.gamma, "env.shaping.gamma",
          f"must equal agent.gamma ({a.gamma}) when env.shaping.weight > 0, got {cfg.env.shaping.gamma}: "
          "the shaping leaves the optimal policy unchanged only with the learner's discount")
    _need(b.priority == 0 or cfg.mode.get("sampling") in (None, "stratified"), "mode.sampling",
          "prioritized replay keeps the demos' stratified share; 'proportional' would be ignored")
    _need(b.capacity >= a.batch_size, "buffer.capacity",
          f"must be >= agent.batch_size ({a.batch_size}), got {b.capacity}")
    _need(cfg.total_frames is not None or cfg.total_episodes is not None, "total_frames",
          "set total_frames or total_episodes (or both)")
    if a.update_mode == "captured":  # CUDA graphs
        from memrl.envs.batched import resolve_device

        _need(resolve_device(cfg.device).type == "cuda", "agent.update_mode",
              f"captured needs a CUDA device (device={cfg.device}); use agent.update_mode=compiled")
    agent_part = int(b.capacity) - int(round(demo_share * int(b.capacity)))
    n_envs = int(cfg.env.num_envs)
    _need(agent_part >= n_envs, "env.num_envs",
          f"{n_envs} envs write {n_envs} transitions per step, more than the {agent_part} the "
          "replay keeps for the agent's data; raise buffer.capacity")


def _need(ok: bool, key: str, message: str) -> None:
    if not ok:
        raise config_error(key, message)
