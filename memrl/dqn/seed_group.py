"""Several runs of one process, their turns taken in order: K seeds of one configuration.

On the CPU, K seeds per process take turns (:meth:`memrl.dqn.loop.Trainer.iterate`, one each in
seed order) rather than stacking their networks: ``python -m memrl.bench seeds`` measured one
update of 5 Table I networks stacked with ``vmap`` at 0.56x of 5 updates in turn here. Each run
keeps its own run folder, checkpoints, learner thread and its own state of the global random
generators (torch, numpy, ``random``), swapped in around its turns: every draw a run makes is
the draw its own single-seed process makes, so its episodes, weights and checkpoints are that
run's (``tests/test_seed_group.py``), and a killed group resumes each run from its checkpoint.

With ``seeds_engine=shared`` the runs' training envs are slices of one batched engine
(:mod:`memrl.envs.shared_engine`) and :func:`run_lockstep` takes the turns: each run goes on
until its next env step (:meth:`Trainer.iterate_steps` pauses there with the step's actions),
then one engine call steps every run's envs. Each run's episodes, weights and checkpoints are
still those of its own process.

Hand-written: TorchRL's collectors and Hydra's launchers run one configuration per process.
"""

from __future__ import annotations

import random
from collections.abc import Generator, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from memrl.dqn.loop import Summary, Trainer
from memrl.envs.shared_engine import SharedEngine
from memrl.stop import Interrupted, interruption, request_stop, stop_requested

_ACTIVE: list[Path | None] = [None]
"""The run folder whose turn it is (None: no run of a group): :func:`active_run`."""


def current_run() -> Path | None:
    """The run folder of the group member whose turn it is, e.g. for a log filter that writes
    each run's lines into its own ``train.log`` (None outside a turn)."""
    return _ACTIVE[0]


@contextmanager
def active_run(run_dir: Path | None) -> Iterator[None]:
    """:func:`current_run` is ``run_dir`` for the block."""
    before, _ACTIVE[0] = _ACTIVE[0], run_dir
    try:
        yield
    finally:
        _ACTIVE[0] = before


@dataclass
class RngState:
    """The global random generators' states."""

    torch_cpu: torch.Tensor
    numpy: Any
    python: Any
    cuda: list[torch.Tensor] | None = None

    @classmethod
    def now(cls) -> RngState:
        return cls(torch.get_rng_state(), np.random.get_state(), random.getstate(),
                   torch.cuda.get_rng_state_all() if torch.cuda.is_initialized() else None)

    def restore(self) -> None:
        torch.set_rng_state(self.torch_cpu)
        np.random.set_state(self.numpy)
        random.setstate(self.python)
        if self.cuda is not None:
            torch.cuda.set_rng_state_all(self.cuda)


@dataclass
class Member:
    """One run of the group: its trainer (None: it had finished before) and its generators."""

    trainer: Trainer | None
    rng: RngState = field(default_factory=RngState.now)
    summary: Summary | None = None
    run_dir: Path | None = None
    """Its folder, :func:`current_run` during its turns."""

    @contextmanager
    def turn(self) -> Iterator[None]:
        """The global generators hold this run's states for the block (and keep them after)."""
        outer = RngState.now()
        self.rng.restore()
        try:
            with active_run(self.run_dir):
                yield
        finally:
            self.rng = RngState.now()
            outer.restore()


def run_turns(members: Sequence[Member]) -> list[Summary]:
    """Train every member to its budget, one turn each in order; returns their summaries. A stop
    (SIGINT / SIGTERM, :mod:`memrl.stop`) saves every member that a checkpoint resumes exactly,
    as a single run does, then raises."""
    live = [m for m in members if m.trainer is not None]
    current: Member | None = None  # whose turn it is
    try:
        for current in live:
            with current.turn():
                current.trainer.begin()  # type: ignore[union-attr]
        while live:
            for current in list(live):
                m, trainer = current, current.trainer
                assert trainer is not None
                with m.turn():
                    if trainer.done():
                        trainer.end_rounds()
                        trainer.close()
                        m.summary = trainer.finish()
                        live.remove(m)
                    else:
                        trainer.iterate()
    except BaseException as err:
        if interruption(err) is not None or stop_requested():
            for m in live:  # the member that saw the stop saved itself; the others save here
                if m is not current and m.trainer is not None and m.trainer.can_stop():
                    with m.turn():
                        m.trainer.save_checkpoint()
        raise
    finally:
        for m in members:
            if m.trainer is not None:
                m.trainer.close()
    out = [m.summary for m in members]
    assert all(s is not None for s in out)
    return out  # type: ignore[return-value]


def run_lockstep(members: Sequence[Member], shared: SharedEngine) -> list[Summary]:
    """:func:`run_turns` for members whose envs are the slices of ``shared``, in member order:
    in each pass every member runs until its next env step and submits its actions (or to the
    end of its budget), then ``shared`` steps them all. A stop (SIGINT / SIGTERM) lets every
    member go on to its next checkpoint, as its own process does; then it is raised."""
    lockstep = _Lockstep([m for m in members if m.trainer is not None])
    try:
        for m in list(lockstep.live):
            lockstep.current = m
            with m.turn():
                m.trainer.begin()  # type: ignore[union-attr]
        while lockstep.live:
            for m in list(lockstep.live):
                lockstep.current = m
                lockstep.advance(m)
            if any(s.submitted is not None for s in shared.slices):
                shared.step()
    except BaseException as err:
        lockstep.abort(err)
        raise
    finally:
        for m in members:
            if m.trainer is not None:
                m.trainer.close()
    if lockstep.stop is not None:
        raise lockstep.stop
    out = [m.summary for m in members]
    assert all(s is not None for s in out)
    return out  # type: ignore[return-value]


@dataclass
class _Lockstep:
    """The members of :func:`run_lockstep` still training, and where each one is."""

    live: list[Member]
    paused: dict[int, Generator[torch.Tensor, None, None]] = field(default_factory=dict)
    """id(member): its iterate, paused before an env step."""
    stop: Interrupted | None = None
    """A member's stop after its checkpoint; the others go on to theirs."""
    current: Member | None = None

    def advance(self, m: Member) -> None:
        """Member ``m`` on to its next env step, its actions submitted; or to its end (its
        budget, or a stop after its checkpoint), and out of :attr:`live`."""
        try:
            with m.turn():
                if self._to_next_step(m):
                    return
        except Interrupted as err:
            assert m.trainer is not None
            if not m.trainer.stopped_saved:
                raise
            self.stop = self.stop or err
            m.trainer.close()
            self.paused.pop(id(m), None)
            if len(self.live) > 1:
                request_stop(err.signum)  # raise_pending cleared it: the others stop too
        self.live.remove(m)

    def _to_next_step(self, m: Member) -> bool:
        """Run ``m`` on to its next env step and submit its actions (True), or to the end of its
        budget (False: its summary set)."""
        trainer = m.trainer
        assert trainer is not None
        while True:
            gen = self.paused.pop(id(m), None)
            if gen is None:
                if trainer.done():
                    trainer.end_rounds()
                    trainer.close()
                    m.summary = trainer.finish()
                    return False
                gen = trainer.iterate_steps()
            try:
                actions = next(gen)
            except StopIteration:
                continue  # that iterate ended; the next one
            self.paused[id(m)] = gen
            trainer.collector.env.base_env.engine.submit(actions)
            return True

    def abort(self, err: BaseException) -> None:
        """After a failure or an immediate stop: paused iterates closed (their update rounds
        joined); on a stop, the members between iterates save, as :func:`run_turns` does."""
        midway = set(self.paused)
        for gen in self.paused.values():
            gen.close()
        self.paused.clear()
        if interruption(err) is None and not stop_requested():
            return
        for m in self.live:
            if m is not self.current and id(m) not in midway and m.trainer is not None \
                    and m.trainer.can_stop():
                with m.turn():
                    m.trainer.save_checkpoint()
