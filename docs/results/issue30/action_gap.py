"""How far apart are the Q-values of the actions? The action gaps of a run's final weights (or of
other weights) on the states of its own replay buffer, against its TD error.

    python docs/results/issue30/action_gap.py <run folder> [--weights <.pt>] [--last 30000]

Draws up to 1,500 states among the rows written in the last ``--last`` env steps of the agent
part (the states the final policy visits) and gives, as 10th / 50th / 90th percentiles:

- ``best - second``: the greedy action's Q minus the next best (any of the 9 actions);
- ``speed gap``: max - min of Q over the three speed changes, at the greedy curvature change;
- ``curvature gap``: max - min over the three curvature changes, at the greedy speed change;
- the share of greedy actions that slow down, keep the speed, speed up;

and, on 2,000 other stored transitions, the mean |Q(s, a) - (r + gamma^m max_a' Q(s', a'))|
(as ``buffer_crash_fit.py``); for a run trained with advantage learning
(``agent.advantage_learning`` = alpha > 0), also the error against its own target, that less
alpha (max_b Q(s, b) - Q(s, a)). When the gaps are below that error, the argmax among them is
decided by the fit's error, not by what the actions do. Reads ``checkpoints/last/buffer`` and
``checkpoints/final.pt`` (or ``--weights``). Written by hand: a diagnostic of finished runs.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
import yaml

from memrl.checkpoint import load_qnet, load_stage1_qnet
from memrl.data.buffers import agent_buffer
from memrl.modules.policy import GreedyPolicy


def percentiles(x: torch.Tensor) -> list[float]:
    return [round(float(x.quantile(p)), 3) for p in (0.1, 0.5, 0.9)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--weights", type=Path, default=None,
                        help="a weights file, or a mode B stage1.pt (default: the run's final.pt)")
    parser.add_argument("--last", type=int, default=30_000,
                        help="env steps at the end of the buffer to draw from")
    args = parser.parse_args()
    torch.set_num_threads(1)
    cfg = yaml.safe_load((args.run / "config.yaml").read_text())
    streams, gamma = int(cfg["env"]["num_envs"]), float(cfg["agent"]["gamma"])
    mode = cfg.get("mode") or {}
    share = {"A": lambda: mode["demo_fraction"], "B": lambda: mode["stage2"]["demo_fraction"]}.get(
        mode.get("name"), lambda: 0.0)()  # the demo slice of modes A and B's stage 2
    capacity = int(cfg["buffer"]["capacity"])
    rb = agent_buffer(capacity - int(round(share * capacity)), 32, streams=streams)  # the agent part
    rb.loads(args.run / "checkpoints" / "last" / "buffer")
    n = len(rb)
    g = torch.Generator().manual_seed(0)
    rows = torch.randperm(n, generator=g)
    late = rows[rows >= n - args.last][:1500]  # one row per env step (all envs counted)
    td = rb.storage.get(late)
    weights = args.weights or args.run / "checkpoints" / "final.pt"
    load = load_stage1_qnet if weights.name == "stage1.pt" else lambda w: load_qnet(w)[0]
    policy = GreedyPolicy(load(weights))
    q = policy.q_values(td["pixels"]).reshape(-1, 3, 3)  # [speed change, curvature change]
    best = q.reshape(-1, 9).argmax(1)
    speed, curv, i = best // 3, best % 3, torch.arange(len(q))
    top2 = q.reshape(-1, 9).topk(2, 1).values
    other = rows[:2000]
    o = rb.storage.get(other)
    q_o = policy.q_values(o["pixels"])
    q_sa = q_o.gather(1, o["action"].unsqueeze(1)).squeeze(1)
    boot = o["next", "reward"].reshape(-1) + gamma * policy.q_values(o["next", "pixels"]).max(1).values * \
        (~o["next", "done"].reshape(-1))
    alpha = float(cfg["agent"].get("advantage_learning", 0.0))  # runs before it: eq. (1)
    extra = {}
    if alpha > 0:
        al_target = boot - alpha * (q_o.max(1).values - q_sa)
        extra = {f"mean |AL TD error| (alpha {alpha:g})": round(float((q_sa - al_target).abs().mean()), 2)}
    print(json.dumps({
        "run": str(args.run), "weights": str(weights), "states": len(q), "mean Q": round(float(q.mean()), 2),
        "best - second p10/50/90": percentiles(top2[:, 0] - top2[:, 1]),
        "speed gap p10/50/90": percentiles(q[i, :, curv].max(1).values - q[i, :, curv].min(1).values),
        "curvature gap p10/50/90": percentiles(q[i, speed, :].max(1).values - q[i, speed, :].min(1).values),
        "greedy slower / keep / faster": [round(float((speed == k).float().mean()), 3) for k in range(3)],
        "mean |TD error| (2,000 stored transitions)": round(float((q_sa - boot).abs().mean()), 2), **extra}))


if __name__ == "__main__":
    main()
