"""The batched engine on CUDA is the reference env's task too (skipped without CUDA).

World state is float64 on every device; sin/cos on the GPU may differ from the CPU's in the
last bit, so states are compared within a tolerance and frames/outcomes exactly.
"""

from __future__ import annotations

import pytest
import torch

from tests.batched_helpers import compare, random_actions

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")

NON_GOAL = {"initial_lane": "non_goal", "vehicles_count": [0, 5]}


def test_cuda_random_actions_match_the_reference():
    tally = compare(NON_GOAL, list(range(32)), 300, random_actions(1.0), device="cuda")
    assert tally.steps == 32 * 300 and tally.resets > 32


def test_cuda_steady_driving_and_path_cue_match_the_reference():
    compare({"bev": {"path_length": 20.0}}, list(range(32, 48)), 310, random_actions(0.0), device="cuda")


def test_cuda_every_cars_path_matches_the_reference():
    config = {"bev": {"path_time": 2.0}, **NON_GOAL}
    compare(config, list(range(500, 516)), 300, random_actions(0.5), device="cuda")


def test_cuda_shaped_rewards_match_the_reference():
    # risk reads the states, which may differ in the last bit here: 1e-6 is far above what
    # 1e-9 of state can move w (risk(s) - gamma risk(s')) unless a gap closes at < 1e-3 m/s
    config = {**NON_GOAL, "shaping": {"weight": 2.0}}
    tally = compare(config, list(range(600, 616)), 200, random_actions(1.0), device="cuda", reward_atol=1e-6)
    assert tally.steps == 16 * 200 and tally.collisions > 0


def test_cuda_engine_runs_thousands_of_envs():
    from memrl.envs.batched import BatchedLaneChange

    engine = BatchedLaneChange({}, 4096, "cuda")
    engine.reset(seeds=list(range(4096)))
    for _ in range(10):
        out = engine.step(torch.randint(0, 9, (4096,), device="cuda"))
        done = torch.nonzero(out.terminated | out.truncated).flatten()
        engine.reset(done)
    assert engine.observation().shape == (4096, 4, 84, 84) and engine.observation().is_cuda
