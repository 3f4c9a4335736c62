"""Several runs of one process, their turns taken in order: K seeds of one configuration.

On the CPU, K seeds per process take turns (:meth:`memrl.dqn.loop.Trainer.iterate`, one each in
seed order) rather than stacking their networks: ``python -m memrl.bench seeds`` measured one
update of 5 Table I networks stacked with ``vmap`` at 0.56x of 5 updates in turn here. Each run
keeps its own run folder, checkpoints, learner thread and its own state of the global random
generators (torch, numpy, ``random``), swapped in around its turns: every draw a run makes is
the draw its own single-seed process makes, so its episodes, weights and checkpoints are that
run's (``tests/test_seed_group.py``), and a killed group resumes each run from its checkpoint.

Hand-written: TorchRL's collectors and Hydra's launchers run one configuration per process.
"""

from __future__ import annotations

import random
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from memrl.dqn.loop import Summary, Trainer
from memrl.stop import interruption, stop_requested

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
