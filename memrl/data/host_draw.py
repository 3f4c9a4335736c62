"""Replay indices drawn on the host, whatever device the storage lives on.

TorchRL's ``RandomSampler`` asks the storage for indices, and ``TensorStorage`` draws them with
``torch.randint(..., device=storage.device)``: on a CUDA storage that is the CUDA generator, so
a CUDA run would replay other transitions than a CPU run of the same seed, and a run resumed on
the other device would switch random streams. :class:`HostDrawStorage` draws them with the CPU
generator (the same call and stream as on a CPU storage) and moves them to the device: the same
seed replays the same transitions on any device (``tests/test_frame_store_cuda.py``).
"""

from __future__ import annotations

import torch
from torchrl.data import LazyTensorStorage

__all__ = ["HostDrawStorage"]


class HostDrawStorage(LazyTensorStorage):
    """``LazyTensorStorage`` whose sampler indices come from the CPU generator (module doc)."""

    def _rand_given_ndim(self, batch_size: int) -> torch.Tensor:
        # by hand: TorchRL draws on the storage's device (its generator, not the CPU's)
        if self.ndim != 1:
            return super()._rand_given_ndim(batch_size)
        index = torch.randint(0, len(self), (batch_size,), generator=self._rng)
        return index.to(self.device, non_blocking=True)
