"""K runs' training envs as one batched engine: each run steps a slice of its rows.

A :class:`SharedEngine` holds one :class:`~memrl.envs.batched.BatchedLaneChange` of K x N envs
and K :class:`EngineSlice` s, each the engine of one run's N envs (rows ``k*N .. k*N + N - 1``):
it resets, observes, reports and checkpoints those rows alone, and its ``state_dict`` is what an
engine of N envs stepped the same way saves. Stepping is in lockstep: every run submits its
actions (:meth:`EngineSlice.submit`), :meth:`SharedEngine.step` steps all rows in one call, and
each run's own ``step`` then returns its rows of that step. Rows do not interact in a step (each
env's scene, physics, collisions, rewards and pictures are its own, its generator too), so a
run's episodes are those of its own engine (``tests/test_shared_engine.py``).

Learned cars are refused: their network would act on K runs' frames in one batch, where a
float32 convolution's result may depend on the batch (and self-play pools differ per run).

Hand-written: TorchRL's batched envs and collectors serve one policy per env batch.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch

from memrl.envs.batched import BatchedLaneChange, StepOut, check_actions
from memrl.envs.batched_state import engine_state, load_engine_state
from memrl.envs.config import BatchedEnvError
from memrl.envs.vehicles import IDLE


class EngineSlice:
    """The engine of one run's ``num_envs`` envs, rows ``start ..`` of a :class:`SharedEngine`
    (the parts of :class:`~memrl.envs.batched.BatchedLaneChange` that a training run uses)."""

    def __init__(self, shared: SharedEngine, start: int, num_envs: int) -> None:
        self.shared, self.start, self.num_envs = shared, start, num_envs
        self.rows = slice(start, start + num_envs)
        e = shared.engine
        self.cfg, self.device, self.frame_stack = e.cfg, e.device, e.frame_stack
        self.frame_stride, self.history, self.learned, self.opponents = (
            e.frame_stride, e.history, e.learned, e.opponents)
        self._ids = torch.arange(start, start + num_envs, device=e.device)
        self._shift = 0  # ring slots between the shared head and this run's own (its loaded one)
        self.submitted: torch.Tensor | None = None
        """Actions of the next shared step (:meth:`submit`), until it is taken."""
        self._out: StepOut | None = None
        self._taken: torch.Tensor | None = None

    def submit(self, actions: Any) -> None:
        """This run's actions ``[N]`` for the next :meth:`SharedEngine.step`."""
        self.submitted = check_actions(actions, self.num_envs, self.device)

    def step(self, actions: Any) -> StepOut:
        """This run's rows of the shared step taken with its submitted ``actions`` (the same)."""
        if self._out is None or self._taken is None:
            raise BatchedEnvError("a shared engine's slice steps with SharedEngine.step(): submit its "
                                  "actions first")
        if not torch.equal(torch.as_tensor(actions, device=self.device), self._taken):  # checked at submit
            raise BatchedEnvError("a slice stepped with other actions than it submitted")
        out, self._out, self._taken = self._out, None, None
        return out

    def reset(self, env_ids: Sequence[int] | torch.Tensor | None = None,
              seeds: Sequence[int | None] | None = None) -> None:
        ids = range(self.num_envs) if env_ids is None else torch.as_tensor(env_ids).reshape(-1).tolist()
        self.shared.engine.reset([self.start + int(i) for i in ids], seeds)

    def observation(self) -> torch.Tensor:
        return self.shared.engine.observation(self._ids)

    def info(self) -> dict[str, torch.Tensor]:
        return _rows(self.shared.engine.info(), self.rows)

    def state_dict(self) -> dict[str, Any]:
        """What an engine of these N envs alone saves (its own ring head)."""
        return engine_state(self.shared.engine, self.rows, self._shift)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self._shift = load_engine_state(self.shared.engine, state, self.rows)

    def _took(self, actions: torch.Tensor, out: StepOut) -> None:
        self._taken, self._out, self.submitted = actions, out, None


class SharedEngine:
    """One batched engine of ``parts`` x ``num_envs`` envs and its ``parts`` slices.

    Args:
        config, device, frame_stack: as for :class:`~memrl.envs.batched.BatchedLaneChange`.
        num_envs: N, the envs of each slice.
        parts: K, the slices (runs).
    """

    def __init__(self, config: Mapping[str, Any] | None, num_envs: int, parts: int,
                 device: torch.device | str | None = "cpu", frame_stack: int = 4) -> None:
        if isinstance(parts, bool) or not isinstance(parts, int) or parts < 1:
            raise BatchedEnvError(f"parts must be an int >= 1, got {parts!r}")
        self.engine = BatchedLaneChange(config, num_envs * parts, device, frame_stack)
        if self.engine.learned is not None:
            raise BatchedEnvError("a shared engine takes no learned cars (their network would act on "
                                  "several runs' frames in one batch); give each run its own engine")
        self.slices = [EngineSlice(self, k * num_envs, num_envs) for k in range(parts)]
        self.steps = 0
        """Shared steps taken."""

    def step(self) -> None:
        """Step every row: each slice's submitted actions; the rows of a slice that submitted
        none (its run has ended) keep speed and curvature (their outcome is nobody's)."""
        e = self.engine
        actions = torch.full((e.num_envs,), IDLE, dtype=torch.int64, device=e.device)
        for s in self.slices:
            if s.submitted is not None:
                actions[s.rows] = s.submitted
        out = e.step(actions)
        for s in self.slices:
            if s.submitted is not None:
                s._took(s.submitted, _rows(out, s.rows))
        self.steps += 1


def _rows(x: Any, rows: slice) -> Any:
    """Rows ``rows`` of every tensor in ``x`` (a StepOut, a dict, a tensor; None stays None)."""
    if isinstance(x, torch.Tensor):
        return x[rows]
    if isinstance(x, dict):
        return {k: _rows(v, rows) for k, v in x.items()}
    if isinstance(x, StepOut):
        return StepOut(**{k: _rows(v, rows) for k, v in vars(x).items()})
    return x
