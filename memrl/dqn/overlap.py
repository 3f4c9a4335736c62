"""The overlap strategy: a round of updates in a learner thread while this thread collects.

Hand-written: TorchRL's collectors run free of the update schedule (no exact resume). Here the
round's batches are sampled before it starts, the learner thread only runs the gradient steps,
the env is stepped in the calling thread with an acting copy of the online network (refreshed
after each round, so it never reads weights the optimizer is writing), and the new transitions
join the buffer after the round: every draw from the global RNGs stays in one thread, in a
fixed order, and runs stay deterministic.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any, TypeVar

import torch
from tensordict import TensorDictBase

from memrl.dqn.learner import Learner

T = TypeVar("T")


class RoundRunner:
    """Runs update rounds inline, or overlapped with collection when ``overlap`` is on.

    Args:
        learner: the learner whose ``update`` runs the rounds.
        overlap: run rounds in a learner thread while the caller collects.
        threads: torch intra-op threads of that thread (0: torch's default).
    """

    def __init__(self, learner: Learner, overlap: bool, threads: int) -> None:
        self.learner, self.overlap, self.threads = learner, overlap, threads
        self._pool: ThreadPoolExecutor | None = None
        self.acting_net: torch.nn.Module = learner.acting_actor
        """The module the acting policy runs (a copy in overlap mode)."""
        if overlap:
            self.acting_net = copy.deepcopy(learner.acting_actor)
            for module in self.acting_net.modules():  # a copied compiled forward calls the original
                module._compiled_call_impl = None
        self.update_seconds = 0.0
        self._batches = False
        self._result: Any = None  # the round start() began: (losses, seconds) or its future
        self.stale = False
        """The acting copy still holds the weights before the last round (see :meth:`flush`)."""

    def run(self, batches: Sequence[TensorDictBase],
            collect: Callable[[], T]) -> tuple[list[torch.Tensor], T]:
        """The updates of ``batches`` and ``collect()``: overlapped, or updates first; their
        losses as the learner left them (:meth:`Learner.step`: not read back)."""
        self.start(batches)
        try:
            out = collect()
        finally:
            losses = self.finish()
        return losses, out

    def start(self, batches: Sequence[TensorDictBase]) -> None:
        """:meth:`run` in two halves around the caller's collection: the updates of ``batches``
        start (in the learner thread when overlapping, else they run now); :meth:`finish`."""
        def learn() -> tuple[list[torch.Tensor], float]:
            t0 = time.perf_counter()
            return [self.learner.step(b) for b in batches], time.perf_counter() - t0

        self._batches = bool(batches)
        if not self.overlap or not batches:
            self._result = learn()
        else:  # the update in the learner thread, the env in the caller's
            self._result = self._thread().submit(learn)

    def finish(self) -> list[torch.Tensor]:
        """The losses of the round :meth:`start` began (waiting for its thread)."""
        result, self._result = self._result, None
        assert result is not None, "start() first"
        losses, seconds = result if isinstance(result, tuple) else result.result()  # re-raises its error
        self.update_seconds += seconds
        if self._batches or self.stale:
            self.sync()
        return losses

    def flush(self, batches: Sequence[TensorDictBase]) -> list[torch.Tensor]:
        """The rounds due at the end of a run, with the acting copy left as it was: the steps a
        longer run (or this one resumed with a larger budget) collects next would be collected
        during these updates, with the weights before them."""
        t0 = time.perf_counter()
        losses = [self.learner.step(b) for b in batches]
        self.update_seconds += time.perf_counter() - t0
        self.stale = self.stale or (bool(batches) and self.acting_net is not self.learner.acting_actor)
        return losses

    def state_dict(self) -> dict[str, Any]:
        """The acting copy when it differs from the online network (after :meth:`flush`)."""
        return {"stale": self.stale,
                "acting": {k: v.cpu() for k, v in self.acting_net.state_dict().items()}
                if self.stale else None}

    def load_state_dict(self, state: dict[str, Any] | None) -> None:
        self.stale = bool(state and state["stale"])
        if state and state["acting"] is not None:
            self.acting_net.load_state_dict(state["acting"])
        else:
            self.sync()

    def sync(self) -> None:
        """Refresh the acting copy from the online network (overlap mode)."""
        self.stale = False
        if self.acting_net is self.learner.acting_actor:
            return
        with torch.no_grad():
            for dst, src in zip(self.acting_net.parameters(), self.learner.acting_actor.parameters(),
                                strict=True):
                dst.copy_(src)

    def _thread(self) -> ThreadPoolExecutor:
        """The one long-lived learner thread, with ``threads`` torch threads of its own (a new
        thread would otherwise start with one per core)."""
        if self._pool is None:
            threads = self.threads

            def init() -> None:
                if threads:
                    torch.set_num_threads(threads)

            self._pool = ThreadPoolExecutor(1, thread_name_prefix="memrl-learn", initializer=init)
        return self._pool

    def close(self) -> None:
        """Stop the learner thread; it restarts on the next overlapped round."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
