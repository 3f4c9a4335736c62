"""Are the crash transitions of a run's own replay buffer fitted? Q(s, a) of its final weights on
the transitions whose target has no bootstrap (the sampled window ends in a crash: the target
is its reward alone), by when they were written, against the TD error of the other transitions.

    python docs/results/issue30/buffer_crash_fit.py <run folder> [--block 10000]

Reads ``checkpoints/last/buffer`` (the agent part: FIFO, written in env-step order, one row per
env per step) and ``checkpoints/final.pt``. Meaningful for a finished run whose buffer was never
overwritten (env steps <= the agent part's capacity), so that a row's position is its write
time. Written by hand: a diagnostic of one finished run, no training code needs it.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
import yaml

from memrl.checkpoint import load_qnet
from memrl.data.buffers import agent_buffer
from memrl.modules.policy import GreedyPolicy


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--block", type=int, default=10_000, help="env steps per row of the table")
    args = parser.parse_args()
    torch.set_num_threads(1)
    cfg = yaml.safe_load((args.run / "config.yaml").read_text())
    streams, gamma = int(cfg["env"]["num_envs"]), float(cfg["agent"]["gamma"])
    n_step = int(cfg["agent"]["n_step"])
    capacity = int(cfg["buffer"]["capacity"])
    mode = cfg.get("mode") or {}
    share = {"A": lambda: mode["demo_fraction"], "B": lambda: mode["stage2"]["demo_fraction"]}.get(
        mode.get("name"), lambda: 0.0)()  # the demo slice of modes A and B's stage 2
    capacity -= int(round(share * capacity))  # the agent part (PriorKnowledgeBuffer's online part)
    rb = agent_buffer(capacity, 32, streams=streams, n_step=n_step, gamma=gamma)
    rb.loads(args.run / "checkpoints" / "last" / "buffer")
    n = len(rb)
    td = rb.storage.get(torch.arange(n))
    policy = GreedyPolicy(load_qnet(args.run / "checkpoints" / "final.pt")[0])
    crash = td["next", "terminated"].reshape(n)
    rows = []
    for lo in range(0, n, args.block):  # one row per env step of one env: rows are env steps
        hi = min(n, lo + args.block)
        idx = crash[lo:hi].nonzero().squeeze(-1) + lo
        if len(idx) == 0:
            continue
        q = policy.q_values(td["pixels"][idx])
        q_sa = q.gather(1, td["action"][idx].unsqueeze(1)).squeeze(1)
        target = td["next", "reward"][idx].reshape(-1)
        rows.append({"env steps": f"{lo}-{hi}",
                     "crash windows": len(idx), "share %": round(100 * len(idx) / (hi - lo), 2),
                     "Q(s,a)": round(q_sa.mean().item(), 2),
                     "max_a Q": round(q.max(1).values.mean().item(), 2),
                     "target": round(target.mean().item(), 2)})
    g = torch.Generator().manual_seed(0)
    others = (~crash).nonzero().squeeze(-1)
    pick = others[torch.randperm(len(others), generator=g)[:2000]]
    q_sa = policy.q_values(td["pixels"][pick]).gather(1, td["action"][pick].unsqueeze(1)).squeeze(1)
    steps = td.get("steps_to_next_obs", torch.ones(n, 1))[pick].reshape(-1).float() if n_step > 1 else 1.0
    boot = td["next", "reward"][pick].reshape(-1) + gamma ** steps * \
        policy.q_values(td["next", "pixels"][pick]).max(1).values * (~td["next", "done"][pick].reshape(-1))
    print(json.dumps({"run": str(args.run), "stored": n, "crash windows": int(crash.sum()), "blocks": rows,
                      "other transitions (2,000 drawn): mean |Q(s,a) - (r + gamma^m max Q(s'))|":
                      round((q_sa - boot).abs().mean().item(), 2)}))


if __name__ == "__main__":
    main()
