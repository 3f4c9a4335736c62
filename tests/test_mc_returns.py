"""Monte-Carlo returns of stored transitions (memrl/data/mc_returns.py) and the stage-1 probe's
calibration of Q(s, a_demo) against them, against hand computations."""

from __future__ import annotations

import math

import numpy as np
import torch
from tensordict import TensorDict
from torch import nn

from memrl.data.mc_returns import continues, mc_returns
from memrl.tools.stage1_probe import calibration


def frame(k: int) -> torch.Tensor:
    return torch.full((1, 2, 2), k, dtype=torch.uint8)


def transitions() -> TensorDict:
    """Three chains. A (rows 0-2): rewards 1, 2, 3, a crash at row 2. B (rows 3-6): rewards 1
    each, a time limit at row 6, whose next frame is row 7's first (the done flag still ends
    the chain). C (rows 7-8): row 8 does not start where row 7 ended (a step cut), no done."""
    pix = [0, 1, 2, 10, 11, 12, 13, 14, 30]
    nxt = [1, 2, 3, 11, 12, 13, 14, 20, 31]
    reward = [1.0, 2.0, 3.0, 1.0, 1.0, 1.0, 1.0, 4.0, 5.0]
    terminated = [False, False, True, False, False, False, False, False, False]
    truncated = [False, False, False, False, False, False, True, False, False]
    n = len(pix)
    done = [a or b for a, b in zip(terminated, truncated, strict=True)]
    flag = lambda v: torch.tensor(v).reshape(n, 1)  # noqa: E731
    return TensorDict({
        "pixels": torch.stack([frame(k) for k in pix]), "action": torch.tensor([0, 1, 2, 3, 4, 5, 6, 7, 8]),
        "next": TensorDict({"pixels": torch.stack([frame(k) for k in nxt]),
                            "reward": torch.tensor(reward).reshape(n, 1), "done": flag(done),
                            "terminated": flag(terminated), "truncated": flag(truncated)}, [n]),
    }, [n])


def test_chains_follow_the_frames_and_stop_at_done():
    assert continues(transitions()).tolist() == [True, True, False, True, True, True, False, False, False]


def test_returns_sum_each_chain_and_are_known_at_a_crash_or_far_from_a_cut():
    g, known = mc_returns(transitions(), gamma=0.5, horizon=2)
    # A: 3; 2 + 0.5 * 3; 1 + 0.5 * 3.5. B: 1; 1.5; 1.75; 1.875. C: 4 and 5, each alone.
    assert g.tolist() == [2.75, 3.5, 3.0, 1.875, 1.75, 1.5, 1.0, 4.0, 5.0]
    # A ends in a crash: known. B's rows 3 and 4 lie 3 and 2 steps before its cut end; 5, 6 nearer.
    assert known.tolist() == [True, True, True, True, True, False, False, False, False]


class Table(nn.Module):
    """Q(s, a) = 10 * (first pixel of s) + a: a network whose values are computed by hand."""

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        return 10.0 * pixels.reshape(len(pixels), -1)[:, :1].float() + torch.arange(9.0)


def test_the_calibration_compares_q_of_the_demo_action_with_the_known_returns():
    cal = calibration(Table(), transitions(), gamma=0.5)
    # at the default horizon of 100 steps only the crash chain A (rows 0-2) is known
    q = np.array([0 + 0, 10 + 1, 20 + 2], dtype=np.float64)
    g = np.array([2.75, 3.5, 3.0])
    assert cal["states"] == 3
    assert math.isclose(cal["q"], q.mean(), rel_tol=0, abs_tol=1e-12)
    assert math.isclose(cal["g"], g.mean(), rel_tol=0, abs_tol=1e-12)
    assert math.isclose(cal["bias"], (q - g).mean(), rel_tol=0, abs_tol=1e-12)
    assert math.isclose(cal["abs"], np.abs(q - g).mean(), rel_tol=0, abs_tol=1e-12)
    assert cal["below"] == 1 / 3  # row 0: Q 0 below its return 2.75
    assert math.isclose(cal["corr"], float(np.corrcoef(q, g)[0, 1]), rel_tol=0, abs_tol=1e-12)
    assert calibration(Table(), transitions()[3:], gamma=0.5) == {"states": 0}  # no crash, no long chain
