"""The same policy and seeds in the plain simulator (the agent's own kinematics, no PID).

The reference the deploy metrics are read against: what the driver does when its commands
take effect instantly and it sees the true state, as in training.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from memrl.control.episode import gray
from memrl.control.metrics import overshoot_of
from memrl.envs.lane_change import LaneChangeEnv
from memrl.modules.policy import DrivingPolicy, FrameStack


def simulator_episode(env: LaneChangeEnv, policy: DrivingPolicy, seed: int,
                      frame_stack: int = 4) -> dict[str, float | bool]:
    """One episode in ``env`` as is; returns collided, reached_target, success, overshoot [m]."""
    obs, _ = env.reset(seed=seed)
    policy.reset(env)
    stack = FrameStack(frame_stack, env.cfg.frame_stride)
    frames = stack.reset(gray(obs)[None])
    start_y = float(env.vehicle.position[1])
    ys, collided = [start_y], False
    while True:  # the evaluation runners' loop, plus the lateral positions and gray RGB frames
        action = int(policy.act(env, frames))
        obs, _, terminated, truncated, info = env.step(action)
        frames = stack.push(gray(obs)[None])
        ys.append(float(env.vehicle.position[1]))
        collided = collided or bool(info["collided"])
        if terminated or truncated:
            break
    reached = bool(env.reached_target)
    return {"collided": collided, "reached_target": reached, "success": reached and not collided,
            "overshoot": overshoot_of(np.array(ys), start_y, env.target_lane * env.cfg.lane_width)}


def simulator_summary(env: LaneChangeEnv, policy: DrivingPolicy,
                      seeds: Sequence[int]) -> dict[str, float | int]:
    """``sim_*`` metrics over ``seeds``, named like the deploy ones."""
    runs = [simulator_episode(env, policy, s) for s in seeds]
    shoots = np.array([r["overshoot"] for r in runs], dtype=np.float64)
    shoots = shoots[~np.isnan(shoots)]
    return {
        "sim_collisions": sum(bool(r["collided"]) for r in runs),
        "sim_success_rate": float(np.mean([r["success"] for r in runs])),
        "sim_overshoot_mean": float(shoots.mean()) if shoots.size else float("nan"),
        "sim_overshoot_max": float(shoots.max()) if shoots.size else float("nan"),
    }
