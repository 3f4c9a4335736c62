"""A shared engine's slices (:mod:`memrl.envs.shared_engine`) give what engines of their own give:
the same frames, rewards and flags step for step, the same checkpoints, and they continue from
an engine's checkpoint saved at another step."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from memrl.envs.batched import BatchedLaneChange
from memrl.envs.config import BatchedEnvError
from memrl.envs.shared_engine import SharedEngine
from tests.helpers import save_pool

K, N = 3, 4
CONFIG = {"vehicles_count": [0, 5], "bev": {"path_time": 2.0}}  # drawn paths, up to 5 other cars


def seeds_of(k: int, count: int, start: int) -> list[int]:
    return [1000 * k + start + i for i in range(count)]


def step_both(shared: SharedEngine, own: list[BatchedLaneChange], actions: list[torch.Tensor]) -> None:
    """One step of every slice and of its own engine, finished episodes reset with new seeds;
    everything each returns must be equal."""
    for s, a in zip(shared.slices, actions, strict=True):
        s.submit(a)
    shared.step()
    for k, (s, e, a) in enumerate(zip(shared.slices, own, actions, strict=True)):
        mine, theirs = s.step(a), e.step(a)
        for name in ("reward", "terminated", "truncated", "collided", "on_target_lane", "reached_target",
                     "crash_kind", "closing_speed"):
            assert torch.equal(getattr(mine, name), getattr(theirs, name)), (k, name)
        assert torch.equal(s.observation(), e.observation()), k
        done = torch.nonzero(theirs.terminated | theirs.truncated).reshape(-1).tolist()
        if done:
            seeds = [int(e.steps.sum()) + 7 * i for i in range(len(done))]
            s.reset(done, seeds)
            e.reset(done, seeds)
            assert torch.equal(s.observation(), e.observation()), k


def fresh(config=CONFIG) -> tuple[SharedEngine, list[BatchedLaneChange]]:
    shared = SharedEngine(config, N, K)
    own = [BatchedLaneChange(config, N) for _ in range(K)]
    for k, (s, e) in enumerate(zip(shared.slices, own, strict=True)):
        s.reset(None, seeds_of(k, N, 0))
        e.reset(None, seeds_of(k, N, 0))
    return shared, own


def test_slices_step_as_engines_of_their_own():
    """300 steps of 3 slices of 4 envs against 3 engines of 4, random actions, resets at episode
    ends: every output equal, and so are the slices' checkpoints and the engines'."""
    shared, own = fresh()
    rng = np.random.default_rng(0)
    ends = 0
    for _ in range(300):
        actions = [torch.as_tensor(rng.integers(0, 9, N)) for _ in range(K)]
        step_both(shared, own, actions)
        ends += sum(int(e.steps.eq(0).sum()) for e in own)
    assert ends > 0  # episodes ended and were reset on the way
    for s, e in zip(shared.slices, own, strict=True):
        assert_same_state(s.state_dict(), e.state_dict())


def assert_same_state(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        if isinstance(a[key], torch.Tensor):
            assert torch.equal(a[key], b[key]), key
        else:
            assert a[key] == b[key], key


def test_a_slice_continues_from_a_checkpoint_saved_at_another_step():
    """Slice 1 loads an engine's state saved 5 steps later than the shared engine's ring stands
    (another head): it goes on exactly as that engine does, and saves that engine's head again."""
    shared, own = fresh()
    rng = np.random.default_rng(1)
    ahead = BatchedLaneChange(CONFIG, N)
    ahead.reset(None, seeds_of(9, N, 0))
    for _ in range(5):
        ahead.step(torch.as_tensor(rng.integers(0, 9, N)))
    assert ahead._head != shared.engine._head
    shared.slices[1].load_state_dict(ahead.state_dict())
    assert_same_state(shared.slices[1].state_dict(), ahead.state_dict())
    own[1] = ahead
    for _ in range(40):
        step_both(shared, own, [torch.as_tensor(rng.integers(0, 9, N)) for _ in range(K)])
    assert_same_state(shared.slices[1].state_dict(), ahead.state_dict())


def test_a_slice_that_submits_nothing_leaves_the_others_alone():
    """A run that ended submits no actions: its rows idle, the others' outcomes are unchanged."""
    shared, own = fresh()
    rng = np.random.default_rng(2)
    for _ in range(20):
        actions = [torch.as_tensor(rng.integers(0, 9, N)) for _ in range(K)]
        for k in (0, 2):
            shared.slices[k].submit(actions[k])
        shared.step()
        for k in (0, 2):
            mine, theirs = shared.slices[k].step(actions[k]), own[k].step(actions[k])
            assert torch.equal(mine.reward, theirs.reward)
            assert torch.equal(shared.slices[k].observation(), own[k].observation())
            done = torch.nonzero(theirs.terminated | theirs.truncated).reshape(-1).tolist()
            if done:
                shared.slices[k].reset(done)
                own[k].reset(done)
    with pytest.raises(BatchedEnvError, match="submit its actions first"):
        shared.slices[1].step(torch.zeros(N, dtype=torch.long))


def test_a_slice_refuses_other_actions_than_it_submitted_and_a_bad_state():
    shared, _ = fresh()
    shared.slices[0].submit(torch.zeros(N, dtype=torch.long))
    shared.step()
    with pytest.raises(BatchedEnvError, match="other actions than it submitted"):
        shared.slices[0].step(torch.ones(N, dtype=torch.long))
    with pytest.raises(BatchedEnvError, match="num_envs: saved 12, this engine 4"):
        shared.slices[0].load_state_dict(shared.engine.state_dict())


def test_learned_cars_are_refused(tmp_path):
    pool = save_pool(tmp_path, seeds=(1,))
    with pytest.raises(BatchedEnvError, match="a shared engine takes no learned cars"):
        SharedEngine({**CONFIG, "opponent": {"type": "learned", "pool": pool}}, N, K)
