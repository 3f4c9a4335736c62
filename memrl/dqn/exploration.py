"""Exploration of the acting policy (``agent.exploration``), for N envs at once.

- ``epsilon``: TorchRL's linearly annealed epsilon-greedy (the paper's setting).
- ``ez_greedy``: temporally-extended epsilon-greedy (Dabney et al., 2021, "Temporally-Extended
  epsilon-Greedy Exploration"): an env that starts exploring repeats one random action for a
  duration drawn from a zeta distribution (``P(n) ~ n^-mu``, ``n <= ez_max_duration``); an
  action here changes speed or curvature for good, so single random steps are undone by the
  next greedy ones and rarely show the agent where a sustained change leads.
- ``speed_only``: epsilon-greedy whose random actions keep the curvature (only speed changes):
  a random curvature step that the policy does not undo drives the car into the road edge.
- ``ez_speed``: ``ez_greedy`` on the speed change alone: an env that starts exploring holds one
  random speed change (slower, keep, faster) for a zeta-distributed duration while the greedy
  action keeps choosing the curvature change. A repeated random curvature change runs the car
  off the road (``ez_greedy``), and single random speed steps are undone by the next greedy ones,
  so neither shows the agent what seconds of braking behind a slower car lead to.
- ``boltzmann``: actions drawn from softmax(Q / T), T annealed linearly from
  ``temperature_start`` to ``temperature_end`` over ``eps_decay_frames`` env steps.

Every module keeps its schedule (and ``ez_greedy`` / ``ez_speed`` their per-env repeats) in
buffers, so the trainer's checkpoints resume it exactly. Each but ``boltzmann`` can apply its last
step's draws to another greedy action (``propose``): what a crash-risk critic's task head
proposed before the mask (``network.task_action=proposed``).
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.data import Categorical, Composite
from torchrl.modules import EGreedyModule

from memrl.dqn.config import EXPLORATIONS, AgentConfig
from memrl.envs.vehicles import ACTIONS, CURVATURE_CHANGES, N_ACTIONS, SPEED_CHANGES

KEEP_CURVATURE = torch.tensor([i for i, (_, dk) in enumerate(ACTIONS) if dk == 0])
"""Action indices that leave the curvature as it is (speed -, =, +)."""


class AlwaysExploring(EGreedyModule):
    """TorchRL's annealed epsilon-greedy, explorative whatever the process-wide exploration type.

    ``EGreedyModule`` acts greedily while ``exploration_type()`` is deterministic, a process
    global that every TorchRL loss sets while it runs: with the learner updating in another
    thread (``agent.overlap``), exploration would switch off at random moments. Same draws
    (``torch.rand``, then the spec's ``rand``) as the parent's explorative branch.
    """

    def step(self, frames: int = 1) -> None:
        """Anneal by ``frames`` env steps in one operation (the parent loops once per frame:
        thousands of tiny kernels per batched step on a GPU)."""
        rate = (self.eps_init - self.eps_end) / self.annealing_num_steps
        self.eps.data.copy_(torch.maximum(self.eps_end, self.eps - rate * frames))

    def _random(self, action: torch.Tensor) -> torch.Tensor:
        spec = self.spec[self.action_key] if isinstance(self.spec, Composite) else self.spec
        spec = spec if spec.shape == action.shape else spec.expand(action.shape)
        return spec.rand().to(action.device)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(self.action_key)
        explore = torch.rand(tensordict.shape, device=self.eps.device) < self.eps
        explore = explore.reshape(explore.shape + (1,) * (action.ndim - explore.ndim))
        drawn = self._random(action)
        self._draws = (explore, drawn)
        tensordict.set(self.action_key, torch.where(explore, drawn, action))
        return tensordict

    def propose(self, greedy: torch.Tensor) -> torch.Tensor:
        """The last :meth:`forward`'s draws applied to ``greedy`` (the shape of its actions)
        instead of the action it was given: the same envs explore, with the same draws."""
        draws = getattr(self, "_draws", None)
        if draws is None:
            raise RuntimeError(f"{type(self).__name__}.propose before any step")
        explore, drawn = draws
        return torch.where(explore, drawn, greedy.reshape(drawn.shape))


class SpeedOnlyExploring(AlwaysExploring):
    """Epsilon-greedy whose random actions only change the speed (curvature kept)."""

    def _random(self, action: torch.Tensor) -> torch.Tensor:
        keep = KEEP_CURVATURE.to(action.device)
        return keep[torch.randint(len(keep), action.shape, device=action.device)]


class EzGreedy(AlwaysExploring):
    """Temporally-extended epsilon-greedy over ``num_envs`` envs (see the module docstring).

    A new episode (``step_count`` 0 in the tensordict) ends any repeat under way.
    """

    choices = N_ACTIONS
    """How many values a repeat draws from (here: the actions)."""

    def __init__(self, *args: Any, num_envs: int = 1, mu: float = 2.0, max_duration: int = 50,
                 **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        device = self.eps.device
        n = torch.arange(1, max_duration + 1, dtype=torch.float64)
        self.register_buffer("durations", (n ** -mu / (n ** -mu).sum()).to(torch.float32).to(device))
        self.register_buffer("remaining", torch.zeros(num_envs, dtype=torch.long, device=device))
        self.register_buffer("repeat", torch.zeros(num_envs, dtype=torch.long, device=device))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        greedy = tensordict.get(self.action_key)
        flat = greedy.reshape(-1)
        n = flat.shape[0]
        step_count = tensordict.get("step_count", None)
        if step_count is not None:  # a new episode ends the repeat under way
            self.remaining.masked_fill_(step_count.reshape(n) == 0, 0)
        start = (self.remaining == 0) & (torch.rand(n, device=self.eps.device) < self.eps)
        length = torch.multinomial(self.durations, n, replacement=True) + 1
        self.repeat.copy_(torch.where(start, torch.randint(self.choices, (n,), device=flat.device),
                                      self.repeat))
        self.remaining.copy_(torch.where(start, length, self.remaining))
        held = self.remaining > 0
        self._draws = (held, self.repeat.clone())
        out = torch.where(held, self._held(flat), flat)
        self.remaining.sub_(1).clamp_(min=0)
        tensordict.set(self.action_key, out.reshape(greedy.shape))
        return tensordict

    def propose(self, greedy: torch.Tensor) -> torch.Tensor:
        draws = getattr(self, "_draws", None)
        if draws is None:
            raise RuntimeError(f"{type(self).__name__}.propose before any step")
        held, repeat = draws
        flat = greedy.reshape(-1)
        return torch.where(held, self._held(flat, repeat), flat).reshape(greedy.shape)

    def _held(self, greedy: torch.Tensor, repeat: torch.Tensor | None = None) -> torch.Tensor:
        """The action of an env mid-repeat, given the greedy actions ``[N]`` (and the repeats:
        default the current ones)."""
        return self.repeat if repeat is None else repeat


class EzSpeed(EzGreedy):
    """``ez_greedy`` on the speed change alone: ``repeat`` holds a speed index (0 slower, 1 keep,
    2 faster) and the curvature change stays the greedy action's (index = 3 speed + curvature)."""

    choices = len(SPEED_CHANGES)

    def _held(self, greedy: torch.Tensor, repeat: torch.Tensor | None = None) -> torch.Tensor:
        repeat = self.repeat if repeat is None else repeat
        return repeat * len(CURVATURE_CHANGES) + greedy % len(CURVATURE_CHANGES)


class Boltzmann(AlwaysExploring):
    """Actions drawn from softmax(Q / T) (``eps`` holds the annealed temperature T)."""

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        q = tensordict.get("action_value")
        action = tensordict.get(self.action_key)
        logits = (q.float() / self.eps.clamp(min=1e-6)).reshape(-1, q.shape[-1])
        drawn = torch.multinomial(torch.softmax(logits, -1), 1).reshape(action.shape)
        tensordict.set(self.action_key, drawn.to(action.dtype))
        return tensordict

    def propose(self, greedy: torch.Tensor) -> torch.Tensor:
        # Its draws come from the values it was given (a risk critic's: masked), not a greedy action.
        raise ValueError("agent.exploration=boltzmann draws from the masked values: it has no "
                         "proposal before the mask (network.task_action=proposed needs another exploration)")


def make_exploration(eps_start: float, eps_end: float, decay_frames: int, kind: str = "epsilon",
                     num_envs: int = 1, *, ez_mu: float = AgentConfig.ez_mu,
                     ez_max_duration: int = AgentConfig.ez_max_duration,
                     temperature_start: float = AgentConfig.temperature_start,
                     temperature_end: float = AgentConfig.temperature_end) -> EGreedyModule:
    """The acting policy's exploration module over the 9 actions.

    Args:
        eps_start, eps_end, decay_frames: the linear schedule of epsilon (``boltzmann``: of the
            temperature, from ``temperature_start`` to ``temperature_end``).
        kind: one of :data:`EXPLORATIONS`.
        num_envs: envs acting together (``ez_greedy`` / ``ez_speed`` keep one repeat per env).
        ez_mu, ez_max_duration, temperature_start, temperature_end: as ``agent.*``
            (:class:`~memrl.dqn.config.AgentConfig`, whose defaults these are).
    """
    spec = Categorical(N_ACTIONS, dtype=torch.int64)
    if kind == "epsilon":
        return AlwaysExploring(spec, eps_init=eps_start, eps_end=eps_end, annealing_num_steps=decay_frames)
    if kind == "speed_only":
        return SpeedOnlyExploring(spec, eps_init=eps_start, eps_end=eps_end,
                                  annealing_num_steps=decay_frames)
    if kind in ("ez_greedy", "ez_speed"):
        repeats = EzGreedy if kind == "ez_greedy" else EzSpeed
        return repeats(spec, eps_init=eps_start, eps_end=eps_end, annealing_num_steps=decay_frames,
                       num_envs=num_envs, mu=float(ez_mu),
                       max_duration=int(ez_max_duration))
    if kind == "boltzmann":
        return Boltzmann(spec, eps_init=float(temperature_start),
                         eps_end=float(temperature_end),
                         annealing_num_steps=decay_frames)
    raise ValueError(f"agent.exploration: unknown {kind!r} (one of {', '.join(EXPLORATIONS)})")
