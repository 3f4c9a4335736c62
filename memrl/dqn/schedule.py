"""When to learn and when to stop: the replay ratio and the budgets, in env steps summed over envs."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class UpdateSchedule:
    """One round of updates every ``train_every`` env steps (summed over the N envs), from
    ``warmup_frames`` on: round k is due once the env steps reach the k-th multiple of
    ``train_every`` that is >= ``warmup_frames``. With N = 1 that is one round at every such env
    step; with N envs a batched step of N env steps makes N / train_every rounds due, so the
    replay ratio (updates per env step) does not depend on N. A round's updates: the stage's
    (``agent.updates_per_round`` unless its spec sets its own, :mod:`memrl.dqn.builder`)."""

    train_every: int
    warmup_frames: int

    def _first(self) -> int:
        """Index (in multiples of ``train_every``) of the first due round's env step."""
        return math.ceil(max(self.warmup_frames, 1) / self.train_every)

    def rounds_due(self, frames: int) -> int:
        """Rounds due in total once ``frames`` env steps are done."""
        return max(0, frames // self.train_every - self._first() + 1)

    def frames_of_round(self, k: int) -> int:
        """Env steps at which round ``k`` (0-based) falls due."""
        return (self._first() + k) * self.train_every

    def steps_to_next_round(self, frames: int, rounds_done: int, num_envs: int) -> int:
        """Batched steps of ``num_envs`` env steps until the next round is due (>= 1)."""
        need = self.frames_of_round(rounds_done) - frames
        return max(1, math.ceil(need / num_envs))


@dataclass(frozen=True)
class Budget:
    """The run's budgets: ``total_frames`` env steps and/or ``total_episodes`` (None: no limit)."""

    total_frames: int | None
    total_episodes: int | None

    def done(self, frames: int, episodes: int) -> bool:
        return ((self.total_frames is not None and frames >= self.total_frames)
                or (self.total_episodes is not None and episodes >= self.total_episodes))

    def steps_left(self, frames: int, num_envs: int) -> int | None:
        """Batched steps until ``total_frames`` is reached (None: no frame budget)."""
        if self.total_frames is None:
            return None
        return max(1, math.ceil((self.total_frames - frames) / num_envs))
