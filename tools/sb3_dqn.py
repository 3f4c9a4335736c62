"""Train a Stable-Baselines3 DQN on ``memrl/LaneChange-v0``: the worked example of evaluating
another library's agent on the Table III scenes (docs/evaluation.md#other-libraries-agents).

    python tools/sb3_dqn.py --steps 50000 --out outputs/sb3/dqn_lane.zip
    python -m memrl.evaluate policy=sb3 policy.path=outputs/sb3/dqn_lane.zip \
        "policy.env={bev:{path_time:2.0}}" hydra.run.dir=outputs/sb3/eval

SB3's own CnnPolicy (NatureCNN) on the observation memrl's runs see (4 stacked frames, every car's
2-s path drawn: ``ENV``), gamma 0.95 and 5 other cars as Table II; everything else is SB3's
DQN defaults but the buffer, which holds each frame stack once (``optimize_memory_usage``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

ENV = {"frame_stack": 4, "bev": {"path_time": 2.0}}
"""The ``gym.make`` config: give the same to ``policy.env`` when evaluating the model."""


def train(steps: int, out: Path, seed: int = 0, buffer_size: int = 50_000) -> Path:
    """Train for ``steps`` env steps and save the model to ``out`` (a ``.zip``)."""
    import gymnasium as gym
    import torch
    from stable_baselines3 import DQN

    import memrl.envs  # noqa: F401  (registers memrl/LaneChange-v0)

    torch.set_num_threads(1)
    env = gym.make("memrl/LaneChange-v0", config=ENV)
    model = DQN("CnnPolicy", env, buffer_size=min(buffer_size, steps), learning_starts=min(1_000, steps // 2),
                gamma=0.95, exploration_fraction=0.2, optimize_memory_usage=True,
                replay_buffer_kwargs={"handle_timeout_termination": False}, seed=seed, device="cpu",
                verbose=0)
    model.learn(total_timesteps=steps)
    out.parent.mkdir(parents=True, exist_ok=True)
    model.save(out)
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=50_000, help="env steps of training")
    parser.add_argument("--out", type=Path, default=Path("outputs/sb3/dqn_lane.zip"))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    print(train(args.steps, args.out, args.seed))


if __name__ == "__main__":
    main()
