"""What an evaluation runs: jobs of episodes, the actor that drives them, their records.

Shared by the gym-env runner (:mod:`memrl.evaluation.runner`) and the batched-engine runner
(:mod:`memrl.evaluation.engine_runner`).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from memrl.envs.lane_change import LaneChangeEnv
from memrl.evaluation.crash_sight import EpisodeTrace
from memrl.evaluation.protocol import EpisodeRecord
from memrl.stop import Interrupted

StepHook = Callable[[LaneChangeEnv, np.ndarray, int | None, EpisodeRecord | None], None]
"""Called after each reset (action None) and each step (the action taken) with the env and
the stacked pixels; the last call of an episode also gets its finished record."""


class Actor(ABC):
    """Chooses the actions of several episodes stepped together (slot = place in the batch)."""

    batchable: bool = True
    """May drive several envs in lockstep."""
    parallel: bool = True
    """May run in worker processes (picklable, opens no window)."""
    needs_render: bool = False
    """Needs ``render_mode='rgb_array'`` (full-scene pictures)."""
    tensor_policy: bool = False
    """Acts from a batch of pixels alone (:meth:`act_pixels`, no env object, no per-episode
    state): :func:`run_jobs` then runs it on the batched engine."""
    needs_steps: bool = False
    """Acts on each episode's step too (:meth:`act_steps`, a roll-in's hand-over at step h):
    the batched engine gives it."""
    gives_values: bool = False
    """Can hand out the network outputs it acts on (:meth:`act_values`): the runners' ``record``
    then keeps them per step (:class:`~memrl.evaluation.crash_sight.EpisodeTrace`)."""

    def begin(self, slot: int, env: LaneChangeEnv, seed: int) -> None:  # noqa: B027
        """A new episode starts in ``slot`` (after the env's reset with ``seed``)."""

    @abstractmethod
    def act(self, slots: Sequence[int], envs: Sequence[LaneChangeEnv], pixels: np.ndarray) -> np.ndarray:
        """Actions (int array ``[B]``) for the running ``slots``; ``pixels`` uint8 ``[B, 4, H, W]``."""

    def act_pixels(self, pixels: torch.Tensor) -> torch.Tensor:
        """Actions (int64 ``[B]``) of uint8 stacks ``[B, 4, H, W]`` (``tensor_policy`` actors)."""
        raise NotImplementedError(f"{type(self).__name__} acts through the env (act)")

    def act_steps(self, pixels: torch.Tensor, steps: torch.Tensor) -> torch.Tensor:
        """Actions (int64 ``[B]``) of uint8 stacks at episode steps ``steps`` ``[B]`` (0: an
        episode's first; ``needs_steps`` actors)."""
        return self.act_pixels(pixels)

    def act_values(self, pixels: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Actions (int64 ``[B]``) of uint8 stacks ``[B, 4, H, W]`` and the outputs they were
        chosen from: ``"q"`` (expected Q-values ``[B, A]``) and, from a network that declares
        one, ``"risk"`` (``[B, A]`` or ``[B]``) (``gives_values`` actors)."""
        raise NotImplementedError(f"{type(self).__name__} gives no Q-values")

    def to(self, device: torch.device | str) -> Actor:  # noqa: B027
        """Run on ``device`` from now on (``tensor_policy`` actors); returns self."""
        return self

    def close(self) -> None:  # noqa: B027
        """Release windows or other resources."""


@dataclass
class Job:
    """Episodes of one initial-lane setting for one process."""

    env: dict[str, Any]
    """Full env config (the protocol's rules applied)."""
    initial_lane: str
    episodes: list[tuple[int, int]]
    """(episode index, reset seed) pairs."""


@dataclass
class JobResult:
    records: list[EpisodeRecord] = field(default_factory=list)
    stopped_early: bool = False
    """A human pressed Esc: the episode under way was dropped, the finished ones kept."""
    interrupted: Interrupted | None = None
    """The signal that stopped it (SIGINT, SIGTERM); None: none did."""
    traces: list[EpisodeTrace] = field(default_factory=list)
    """Per finished episode, its steps' Q-values, actions and rewards (runs with ``record``
    and a ``gives_values`` actor; else empty)."""


@contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """torch on ``n`` CPU threads for the block (the previous count restored after)."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def module_device(module: torch.nn.Module) -> torch.device:
    """Where a network's parameters live (the CPU for one without parameters)."""
    return next((p.device for p in module.parameters()), torch.device("cpu"))
