"""The frame store on a CUDA device: ring, rows and samples stay there, and equal a CPU
full-stack reference (skipped without CUDA; the same torch code runs on CPU in
``test_frame_streams.py`` with ``numpy=False``)."""

from __future__ import annotations

import pytest
import torch
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from memrl.data.buffers import PriorKnowledgeBuffer, agent_buffer
from memrl.data.frame_store import FrameStackStorage
from tests.stream_data import stream_steps
from tests.test_frame_streams import same

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")

DEVICE = "cuda"


def reference(capacity: int) -> TensorDictReplayBuffer:
    return TensorDictReplayBuffer(storage=LazyTensorStorage(capacity), batch_size=16)


@pytest.mark.parametrize("streams", [3, 16])
def test_a_cuda_store_equals_the_cpu_reference_and_stays_on_the_device(streams):
    capacity = 5 * streams + 7
    data = stream_steps(streams, 60, seed=streams)
    rb = agent_buffer(capacity, 16, streams=streams, device=DEVICE)
    ref = reference(capacity)
    store = rb.storage
    assert isinstance(store, FrameStackStorage)
    for t, step in enumerate(data):
        rb.extend(step.to(DEVICE) if t % 2 else step)  # from either side, as a trainer may
        ref.extend(step)
        idx = torch.arange(len(ref))
        got = store.get(idx)
        assert got["pixels"].device.type == "cuda" and got["next", "pixels"].is_cuda
        assert same(got.cpu(), ref.storage.get(idx))
    assert store._ring is not None and store._ring.is_cuda
    assert store._storage["frame_refs"].is_cuda
    for seed in range(3):
        torch.manual_seed(seed)
        x = rb.sample()
        torch.manual_seed(seed)
        y = ref.sample()
        assert x["pixels"].is_cuda and same(x.cpu(), y)


def test_cuda_checkpoints_resume_exactly(tmp_path):
    data = stream_steps(4, 40, seed=1)
    a, ref = agent_buffer(30, 8, streams=4, device=DEVICE), reference(30)
    for step in data[:20]:
        a.extend(step)
        ref.extend(step)
    a.dumps(tmp_path / "rb")
    b = agent_buffer(30, 8, streams=4, device=DEVICE)
    b.loads(tmp_path / "rb")
    for step in data[20:]:
        b.extend(step)
        ref.extend(step)
    idx = torch.arange(30)
    assert b.storage._ring.is_cuda
    assert same(b.storage.get(idx).cpu(), ref.storage.get(idx))


def test_mode_a_on_cuda_with_streams():
    demos = stream_steps(1, 30, seed=9)
    demos = torch.cat(demos)
    demos["is_demo"] = torch.ones(len(demos), dtype=torch.bool)
    gpu = PriorKnowledgeBuffer(demos, capacity=100, demo_fraction=0.1, batch_size=16,
                               streams=4, device=DEVICE)
    cpu = PriorKnowledgeBuffer(demos, capacity=100, demo_fraction=0.1, batch_size=16,
                               streams=4, compact=False)
    for step in stream_steps(4, 40, seed=4):
        gpu.extend(step)
        cpu.extend(step)
    for seed in range(3):
        torch.manual_seed(seed)
        x = gpu.sample()
        torch.manual_seed(seed)
        y = cpu.sample()
        assert x["pixels"].is_cuda and same(x.cpu(), y)
