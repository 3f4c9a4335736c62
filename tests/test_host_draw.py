"""Replay indices come from the CPU generator on any storage device (memrl.data.host_draw);
on the CPU they equal TorchRL's own draw (the CUDA side: tests/test_frame_store_cuda.py)."""

from __future__ import annotations

import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from memrl.data.host_draw import HostDrawStorage


def test_host_draw_replays_what_torchrl_replays_on_the_cpu():
    data = TensorDict({"x": torch.arange(50)}, batch_size=[50])
    ours = TensorDictReplayBuffer(storage=HostDrawStorage(64), batch_size=16)
    ref = TensorDictReplayBuffer(storage=LazyTensorStorage(64), batch_size=16)
    ours.extend(data)
    ref.extend(data)
    for seed in range(3):
        torch.manual_seed(seed)
        x = ours.sample()["x"]
        torch.manual_seed(seed)
        assert torch.equal(x, ref.sample()["x"])


def test_host_draw_uses_the_cpu_generator_and_no_other_draw():
    store = HostDrawStorage(64)
    store.set(torch.arange(40), TensorDict({"x": torch.arange(40)}, batch_size=[40]))
    torch.manual_seed(7)
    idx = store._rand_given_ndim(1000)
    torch.manual_seed(7)
    assert torch.equal(idx, torch.randint(0, 40, (1000,)))
    assert idx.min() >= 0 and idx.max() < 40 and idx.device.type == "cpu"
