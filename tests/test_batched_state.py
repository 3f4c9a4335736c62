"""The batched engine's state dict: a mid-episode checkpoint resumes bit-exactly."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from memrl.envs.batched import BatchedEnvError, BatchedLaneChange
from tests.helpers import save_pool

N = 12
NON_GOAL = {"initial_lane": "non_goal", "vehicles_count": [0, 5]}


@pytest.fixture(scope="module")
def pool(tmp_path_factory):
    return save_pool(tmp_path_factory.mktemp("pool"), head_scale=100.0)


def _run(engine: BatchedLaneChange, rng: np.random.Generator, steps: int) -> list[dict[str, np.ndarray]]:
    """``steps`` steps of random actions (finished envs reset); what each step gave."""
    seen = []
    for _ in range(steps):
        actions = torch.as_tensor(rng.integers(9, size=engine.num_envs))
        out = engine.step(actions)
        done = torch.nonzero(out.terminated | out.truncated).flatten()
        if len(done):
            engine.reset(done)
        keys = ("reward", "terminated", "truncated", "collided", "on_target_lane", "reached_target")
        record = {k: getattr(out, k).cpu().numpy() for k in keys}
        record.update({f"components/{k}": v.cpu().numpy() for k, v in out.components.items()})
        record["obs"] = engine.observation().cpu().numpy()
        record["state"] = engine.state.cpu().numpy()
        record["present"] = engine.present.cpu().numpy()
        record["steps"] = engine.steps.cpu().numpy()
        if engine._car_frames is not None:
            record["car_frames"] = engine._car_frames.cpu().numpy()
        seen.append(record)
    return seen


@pytest.mark.parametrize(("kind", "stride"), [("constant", 1), ("learned", 1), ("mixed", 1), ("constant", 3)])
def test_a_saved_and_reloaded_engine_continues_exactly_as_the_original(tmp_path, pool, kind, stride):
    config = {**NON_GOAL, "frame_stride": stride}  # stride 3: a ring of 10 frames, cars' too
    if kind != "constant":  # exploration draws from each env's generator: it must be restored too
        config = {**config, "vehicles_count": 4, "opponent": {"type": kind, "pool": pool, "epsilon": 0.2}}
    engine = BatchedLaneChange(config, N)
    engine.reset(seeds=list(range(N)))
    rng = np.random.default_rng(0)
    before = _run(engine, rng, 60)
    assert sum(int((r["terminated"] | r["truncated"]).sum()) for r in before) > 0  # resets happened
    assert (engine.steps > 0).any()  # mid-episode
    torch.save(engine.state_dict(), tmp_path / "engine.pt")
    if kind != "constant":
        assert bool(engine.is_learned.any())
    resumed = BatchedLaneChange(config, N)
    resumed.load_state_dict(torch.load(tmp_path / "engine.pt"))
    assert np.array_equal(resumed.observation().numpy(), engine.observation().numpy())
    continued = _run(engine, np.random.default_rng(1), 80)
    replayed = _run(resumed, np.random.default_rng(1), 80)
    for a, b in zip(continued, replayed, strict=True):
        assert a.keys() == b.keys()
        for key in a:
            assert np.array_equal(a[key], b[key]), key
    assert sum(int(r["terminated"].sum()) for r in continued) > 0  # crashes and resets after the load


def test_learned_cars_frame_histories_resume_exactly_at_stride_3(tmp_path, pool):
    """Mid-episode at k = 3: the ring and each learned car's 10 frames come back bit-exact."""
    config = {"vehicles_count": 2, "frame_stride": 3, "opponent": {"type": "learned", "pool": pool}}
    engine = BatchedLaneChange(config, 3)
    engine.reset(seeds=[0, 1, 2])
    _run(engine, np.random.default_rng(0), 8)
    assert engine._car_frames is not None and engine._car_frames.shape[2] == 10
    torch.save(engine.state_dict(), tmp_path / "engine.pt")
    resumed = BatchedLaneChange(config, 3)
    resumed.load_state_dict(torch.load(tmp_path / "engine.pt"))
    continued = _run(engine, np.random.default_rng(1), 15)
    replayed = _run(resumed, np.random.default_rng(1), 15)
    for a, b in zip(continued, replayed, strict=True):
        for key in a:
            assert np.array_equal(a[key], b[key]), key


def test_state_dict_is_a_copy_not_a_view_of_the_running_engine():
    engine = BatchedLaneChange({}, 3)
    engine.reset(seeds=[0, 1, 2])
    state = engine.state_dict()
    frames, cars = state["frames"].clone(), state["state"].clone()
    for _ in range(3):
        engine.step(torch.full((3,), 7))
    assert torch.equal(state["frames"], frames) and torch.equal(state["state"], cars)


def test_envs_never_reset_keep_no_generator():
    engine = BatchedLaneChange({}, 2)
    engine.reset([1], seeds=[5])
    state = engine.state_dict()
    assert state["rngs"][0] is None and state["rngs"][1] is not None
    other = BatchedLaneChange({}, 2)
    other.load_state_dict(state)
    assert other.rngs[0] is None
    assert other.rngs[1].bit_generator.state == engine.rngs[1].bit_generator.state


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"num_envs": 3}, "num_envs: saved 2, this engine 3"),
    ({"frame_stack": 2}, "frame_stack: saved 4, this engine 2"),
    ({"config": {"duration": 100}}, "config duration: saved 300, this engine 100"),
    ({"config": {"vehicles_count": 3}}, "car_slots: saved 6, this engine 4"),
    ({"config": {"frame_stride": 3}}, "frame_stride: saved 1, this engine 3"),
])
def test_loading_into_a_different_engine_names_what_differs(kwargs, match):
    engine = BatchedLaneChange({}, 2)
    engine.reset(seeds=[0, 1])
    other = BatchedLaneChange(**{"config": {}, "num_envs": 2, **kwargs})
    with pytest.raises(BatchedEnvError, match=match):
        other.load_state_dict(engine.state_dict())


def test_a_state_saved_before_frame_stride_existed_loads_at_stride_1():
    engine = BatchedLaneChange({}, 2)
    engine.reset(seeds=[0, 1])
    engine.step(torch.full((2,), 3))
    state = engine.state_dict()
    del state["frame_stride"], state["config"]["frame_stride"]  # as saved by the older version
    other = BatchedLaneChange({}, 2)
    other.load_state_dict(state)
    assert torch.equal(other.observation(), engine.observation())
    with pytest.raises(BatchedEnvError, match="frame_stride: saved 1, this engine 2"):
        BatchedLaneChange({"frame_stride": 2}, 2).load_state_dict(state)


def test_a_state_saved_before_path_time_existed_loads_with_the_cue_off():
    engine = BatchedLaneChange({}, 2)
    engine.reset(seeds=[0, 1])
    state = engine.state_dict()
    assert state["config"].pop("bev.path_time") == 0.0  # as saved by the older version
    BatchedLaneChange({}, 2).load_state_dict(state)
    with pytest.raises(BatchedEnvError, match="config bev.path_time: saved 0.0, this engine 2.0"):
        BatchedLaneChange({"bev": {"path_time": 2.0}}, 2).load_state_dict(state)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_a_state_saved_on_cuda_loads_on_cpu(tmp_path):
    gpu = BatchedLaneChange({}, 4, "cuda")
    gpu.reset(seeds=list(range(4)))
    for _ in range(10):
        gpu.step(torch.full((4,), 5, device="cuda"))
    torch.save(gpu.state_dict(), tmp_path / "engine.pt")
    cpu = BatchedLaneChange({}, 4, "cpu")
    cpu.load_state_dict(torch.load(tmp_path / "engine.pt"))
    assert cpu.state.device.type == "cpu"
    assert torch.equal(cpu.observation(), gpu.observation().cpu())
    assert torch.equal(cpu.state, gpu.state.cpu())
