"""Oversampling of crash transitions in the agent's replay (``buffer.crash_share``).

Crashes are rare in the agent's data once it drives (0.3-0.5% of the transitions of a Default
run after 50,000 env steps), and a transition of the FIFO buffer is sampled about
``batch / train_every`` = 8 times while it is stored, so the late crashes, those of the policy
that is evaluated, are fitted least: the final weights of a Default run value its own crash
transitions of the last 30,000 env steps at Q 12-25 against a target of -5
(``docs/results/issue30/screens.md``, section 11). :class:`CrashShareSampler` draws
``round(share * batch)`` items of every batch uniformly from the stored transitions that end
in a crash (``("next", "terminated")``: the only termination of the lane-change env) and the
rest uniformly from all stored transitions. The TD targets are unchanged; only how often each
transition is fitted changes (as a prioritized replay without importance weights would, but
by a fixed share: TorchRL's ``PrioritizedSampler`` needs a compiled extension that the
project's torch build lacks).
"""

from __future__ import annotations

from typing import Any

import torch
from torchrl.data.replay_buffers.samplers import RandomSampler
from torchrl.data.replay_buffers.storages import Storage

CRASH_KEY = ("next", "terminated")


def crash_rows(storage: Storage) -> torch.Tensor:
    """Row indices (CPU int64) of the stored transitions that end in a crash."""
    n = len(storage)
    stored = getattr(storage, "_storage", None)
    if n == 0 or stored is None:
        return torch.zeros(0, dtype=torch.int64)
    flags = stored.get(CRASH_KEY)[:n]
    return flags.reshape(n, -1).any(-1).cpu().nonzero().squeeze(-1)


class CrashShareSampler(RandomSampler):
    """Uniform sampling with ``round(share * batch)`` items of each batch drawn from the crash
    transitions (all uniform while none is stored).

    Stateless beyond torch's global generator, as TorchRL's ``RandomSampler``: a resumed run
    that restores that generator samples exactly what the uninterrupted one would.
    """

    # Hand-written: TorchRL's samplers weight items by priority (PrioritizedSampler, not
    # loadable on the project's torch build) or not at all; none holds a fixed share.
    def __init__(self, share: float) -> None:
        if not 0.0 <= share < 1.0:
            raise ValueError(f"crash share must be in [0, 1), got {share}")
        super().__init__()
        self.share = float(share)

    def sample(self, storage: Storage, batch_size: int) -> tuple[torch.Tensor, dict[str, Any]]:
        k = int(round(self.share * batch_size))
        crashes = crash_rows(storage) if k > 0 else None
        if crashes is None or len(crashes) == 0:
            return super().sample(storage, batch_size)
        picked = crashes[torch.randint(len(crashes), (k,))]
        rest = storage._rand_given_ndim(batch_size - k)  # what RandomSampler draws
        return torch.cat([picked.to(rest.device), rest]), {}
