"""Does the Q-network see a crash coming? Q(s_t, a_t) against the return the episode gave.

Replays the non-goal episodes of an evaluation (``eval.json``: the same scenes, the same greedy
policy, so the same episodes as the scores counted) with the evaluated weights, and writes, per
step, the Q-value of the action taken and the discounted return from that step on,
G_t = sum_k gamma^k r_{t+k} (gamma of the run's config; a crash ends the sum: it is terminal).
Steps are grouped by how many steps before the crash they are (crash episodes) or taken from
survivors' episodes up to 100 steps before the time limit (their truncated sums miss at most
gamma^100 of the tail). A network that sees a crash coming has Q close to G on the crash
episodes' last steps; one that does not, values them like a survivor's steps.

    python docs/results/issue30/q_calibration.py <eval folder or eval.json> [--weights stage1]

Written by hand: the evaluation runner keeps scores, not per-step Q-values (it would cost the
protocol's speed to carry them).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
import yaml

from memrl.checkpoint import load_qnet, load_stage1_qnet
from memrl.envs.lane_change import LaneChangeEnv
from memrl.evaluation.protocol import ProtocolConfig, protocol_env
from memrl.evaluation.results import EVAL_JSON, read_result
from memrl.modules.policy import FrameStack, GreedyPolicy

BUCKETS = [(1, 1), (2, 2), (3, 5), (6, 10), (11, 20), (21, 40), (41, 300)]
"""Steps before the crash (1: the step whose action ended in the crash)."""
TAIL = 100
"""Survivors' steps kept: those at least this many steps before the time limit."""


def returns(rewards: list[float], gamma: float) -> np.ndarray:
    """G_t for every t of one episode (no bootstrap after the last reward)."""
    g, out = 0.0, np.zeros(len(rewards))
    for t in range(len(rewards) - 1, -1, -1):
        g = rewards[t] + gamma * g
        out[t] = g
    return out


def replay(policy: GreedyPolicy, env_cfg: dict, seeds: list[int], frame_stack: int, batch: int = 10
           ) -> list[tuple[np.ndarray, list[float], list[int], bool]]:
    """Per episode: Q-values of the actions taken, rewards, actions, crashed."""
    out = []
    for start in range(0, len(seeds), batch):
        envs = [LaneChangeEnv(config=env_cfg) for _ in seeds[start:start + batch]]
        stacks, qs, rs, acts, done, crashed = [], [], [], [], [], []
        for env, seed in zip(envs, seeds[start:start + batch], strict=True):
            obs, _ = env.reset(seed=seed)
            stacks.append(FrameStack(frame_stack, env.cfg.frame_stride))
            stacks[-1].reset(obs)
            qs.append([]), rs.append([]), acts.append([]), done.append(False), crashed.append(False)
        while not all(done):
            live = [i for i in range(len(envs)) if not done[i]]
            q = policy.q_values(torch.from_numpy(np.stack([stacks[i].frames for i in live]))).numpy()
            for i, qi in zip(live, q, strict=True):
                a = int(qi.argmax())
                obs, r, term, trunc, info = envs[i].step(a)
                stacks[i].push(obs)
                qs[i].append(float(qi[a])), rs[i].append(float(r)), acts[i].append(a)
                if term or trunc:
                    done[i], crashed[i] = True, bool(envs[i].vehicle.crashed or term)
        for i, env in enumerate(envs):
            env.close()
            out.append((np.array(qs[i]), rs[i], acts[i], crashed[i]))
    return out


def table(episodes: list[tuple[np.ndarray, list[float], list[int], bool]], gamma: float, duration: int
          ) -> list[dict]:
    """Mean Q(s_t, a_t), mean G_t and their gap per group of steps."""
    groups: dict[str, list[tuple[float, float]]] = {f"{a}-{b} before crash": [] for a, b in BUCKETS}
    groups["survivors"] = []
    for q, rewards, _, crashed in episodes:
        g = returns(rewards, gamma)
        n = len(rewards)
        for t in range(n):
            if crashed:
                before = n - t
                for a, b in BUCKETS:
                    if a <= before <= b:
                        groups[f"{a}-{b} before crash"].append((q[t], g[t]))
            elif t < duration - TAIL:
                groups["survivors"].append((q[t], g[t]))
    rows = []
    for name, pairs in groups.items():
        if pairs:
            arr = np.array(pairs)
            rows.append({"steps": name, "n": len(arr), "Q": float(arr[:, 0].mean()),
                         "G": float(arr[:, 1].mean()), "Q - G": float((arr[:, 0] - arr[:, 1]).mean())})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("evaluation", type=Path, help="an evaluation folder or its eval.json")
    parser.add_argument("--weights", default="final",
                        help="final (the run's) or stage1 (B's stage-1 weights)")
    parser.add_argument("--episodes", type=int, default=100, help="non-goal episodes replayed")
    args = parser.parse_args()
    file = args.evaluation if args.evaluation.suffix == ".json" else args.evaluation / EVAL_JSON
    result = read_result(file)
    run = Path(result.meta["run"])
    weights = run / "checkpoints" / ("stage1.pt" if args.weights == "stage1" else "final.pt")
    net = load_stage1_qnet(weights) if args.weights == "stage1" else load_qnet(weights)[0]
    torch.set_num_threads(1)
    gamma = float(yaml.safe_load((run / "config.yaml").read_text())["agent"]["gamma"])
    protocol = ProtocolConfig(**result.protocol)
    env_cfg = protocol_env(result.env, protocol, "non_goal")
    episodes = replay(GreedyPolicy(net), env_cfg, result.seeds[:args.episodes], 4)  # the runners stack 4
    crashes = sum(e[3] for e in episodes)
    print(json.dumps({"weights": str(weights), "gamma": gamma, "episodes": len(episodes), "crashes": crashes,
                      "rows": table(episodes, gamma, protocol.duration)}))


if __name__ == "__main__":
    main()
