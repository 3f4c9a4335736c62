"""DAgger (Ross et al. 2011) with the scripted driver as the expert: a ceiling for what the
Table I network can learn from the agent's observation.

Iteration 0 drives the expert itself; iteration k >= 1 drives the network trained so far
(greedy), with the expert's action taken instead with probability ``beta`` per step. Every
visited state is labelled with the expert's action (:class:`~memrl.imitation.expert.ExpertLabeler`)
and added to one dataset that grows over the iterations (aggregation); after each iteration
the network is trained on all of it.

Loss: cross-entropy of the network's 9 outputs (as logits) against the expert's action. The
network is only ever used greedily here (argmax of its outputs, as the evaluation does), so a
classification loss is the direct objective; DQfD's large-margin loss matters when the same
outputs must also stay Q-values for TD updates, which DAgger has none of.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from torchrl.envs.utils import step_mdp

from memrl.checkpoint import save_qnet
from memrl.dqn.collector import episode_seed
from memrl.envs.torchrl_env import env_kwargs, make_env
from memrl.imitation.expert import ExpertLabeler
from memrl.modules.qnet import QNetwork, make_q_actor

log = logging.getLogger(__name__)


@dataclass
class IterationLog:
    """One DAgger iteration (a row of ``dagger.csv``)."""

    iteration: int
    collected: int
    """States visited (and labelled) in this iteration."""
    dataset: int
    """Labelled states in the aggregated dataset after it."""
    episodes: int
    """Episodes that ended in this iteration's driving."""
    survival: float
    """Of those, % without a collision (the driver of the iteration: expert, learner or mix)."""
    goal: float
    """Of those, % that reached the target lane."""
    agreement: float
    """% of this iteration's states where the driving network's greedy action was the expert's
    (iteration 0: the network before any training)."""
    loss: float
    """Mean cross-entropy of the last training epoch."""
    train_accuracy: float
    """% of the aggregated dataset the trained network labels as the expert does."""


@dataclass
class Dataset:
    """The aggregated labelled states: observations ``[M, S, H, W]`` uint8 and labels ``[M]``."""

    obs: list[torch.Tensor] = field(default_factory=list)
    labels: list[torch.Tensor] = field(default_factory=list)
    iteration: list[torch.Tensor] = field(default_factory=list)
    """Which iteration labelled each state."""

    def add(self, obs: torch.Tensor, labels: torch.Tensor, iteration: int) -> None:
        self.obs.append(obs.cpu())
        self.labels.append(labels.cpu())
        self.iteration.append(torch.full((len(labels),), iteration, dtype=torch.long))

    def __len__(self) -> int:
        return sum(len(x) for x in self.labels)

    def tensors(self) -> tuple[torch.Tensor, torch.Tensor]:
        return torch.cat(self.obs), torch.cat(self.labels)


def build_net(cfg: DictConfig, frames: int) -> QNetwork:
    """The Table I network, built as the trainer builds it (``make_q_actor``, ``agent.pool_first``)."""
    return make_q_actor(frames=frames, pool_first=bool(cfg.agent.pool_first)).module[0].module


def greedy(net: QNetwork, pixels: torch.Tensor) -> torch.Tensor:
    with torch.no_grad():
        return net(pixels).argmax(-1)


def train_epochs(net: QNetwork, opt: torch.optim.Optimizer, data: Dataset, epochs: int, batch_size: int,
                 gen: torch.Generator) -> tuple[float, float]:
    """``epochs`` passes of cross-entropy over the dataset; (last epoch's mean loss, accuracy %)."""
    obs, labels = data.tensors()
    loss_sum = 0.0
    net.train()
    for _ in range(epochs):
        order = torch.randperm(len(labels), generator=gen)
        loss_sum = 0.0
        for start in range(0, len(order), batch_size):
            idx = order[start:start + batch_size]
            loss = F.cross_entropy(net(obs[idx]), labels[idx])
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            loss_sum += float(loss.detach()) * len(idx)
    net.eval()
    hits = sum(int((greedy(net, obs[s:s + 1024]) == labels[s:s + 1024]).sum())
               for s in range(0, len(labels), 1024))
    return loss_sum / len(labels), 100.0 * hits / len(labels)


class Driver:
    """Drives the batched engine (the trainer's TorchRL env), labels every state with the expert."""

    def __init__(self, cfg: DictConfig) -> None:
        n = int(cfg.env.num_envs)
        self.env = make_env(env_kwargs(cfg.env), num_envs=n, device="cpu")
        self.engine = self.env.base_env.engine
        self.n, self.seed, self.started = n, int(cfg.seed), 0
        self.labeler = ExpertLabeler(self.engine, lambda: instantiate(cfg.demos.policy))
        self.rng = np.random.default_rng(int(cfg.seed))
        self.td = self._reset(list(range(n)), None)

    def _reset(self, ids: list[int], td: Any) -> Any:
        per_env: list[int | None] = [None] * self.n
        for j, i in enumerate(ids):
            per_env[i] = episode_seed(self.seed, self.started + j)
        self.started += len(ids)
        self.env.base_env.seed_next_reset(per_env)
        self.labeler.new_episodes(ids)
        if td is None:
            return self.env.reset()
        mask = torch.zeros(self.n, 1, dtype=torch.bool)
        mask[ids] = True
        td.set("_reset", mask)
        return self.env.reset(td)

    def collect(self, steps: int, net: QNetwork | None, beta: float
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, list[tuple[bool, bool]]]:
        """``steps`` env steps per env: the visited observations, the expert's labels, the
        network's greedy actions there, and (collided, reached) of each episode that ended.
        ``net`` None: the expert drives; else the network, the expert with probability ``beta``."""
        obs, labels, chosen, ends = [], [], [], []
        for _ in range(steps):
            pixels = self.td["pixels"].clone()
            expert = torch.from_numpy(self.labeler.labels())
            mine = greedy(net, pixels) if net is not None else expert
            take_expert = torch.from_numpy(self.rng.random(self.n) < beta) if net is not None \
                else torch.ones(self.n, dtype=torch.bool)
            obs.append(pixels)
            labels.append(expert)
            chosen.append(mine)
            self.td["action"] = torch.where(take_expert, expert, mine)
            self.td = self.env.step(self.td)
            nxt = self.td["next"]
            done = nxt["done"].reshape(self.n)
            ids = torch.nonzero(done).flatten().tolist()
            ends += [(bool(nxt["collided"][i]), bool(nxt["reached_target"][i])) for i in ids]
            self.td = step_mdp(self.td)
            if ids:
                self.td = self._reset(ids, self.td)
        return torch.cat(obs), torch.cat(labels), torch.cat(chosen), ends


def run_dagger(cfg: DictConfig, out_dir: Path) -> list[IterationLog]:
    """Run ``cfg.iterations`` DAgger iterations; write the run folder (see :mod:`memrl.dagger`)."""
    if cfg.agent.threads:
        torch.set_num_threads(int(cfg.agent.threads))
    torch.manual_seed(int(cfg.seed))
    gen = torch.Generator().manual_seed(int(cfg.seed))
    start = time.perf_counter()
    driver = Driver(cfg)
    net = build_net(cfg, int(driver.td["pixels"].shape[-3]))
    net.eval()
    opt = torch.optim.Adam(net.parameters(), lr=float(cfg.lr))
    data, logs = Dataset(), []
    env_cfg = OmegaConf.to_container(cfg.env, resolve=True)
    for it in range(int(cfg.iterations)):
        obs, labels, mine, ends = driver.collect(int(cfg.steps_per_iteration), net if it > 0 else None,
                                                 float(cfg.beta))
        if it == 0:
            mine = greedy(net, obs)
        data.add(obs, labels, it)
        loss, acc = train_epochs(net, opt, data, int(cfg.epochs), int(cfg.batch_size), gen)
        n_ep = len(ends)
        row = IterationLog(
            iteration=it, collected=len(labels), dataset=len(data), episodes=n_ep,
            survival=100.0 * sum(not c for c, _ in ends) / n_ep if n_ep else float("nan"),
            goal=100.0 * sum(r for _, r in ends) / n_ep if n_ep else float("nan"),
            agreement=100.0 * float((mine == labels).float().mean()), loss=loss, train_accuracy=acc)
        logs.append(row)
        log.info("iteration %d: %d states (dataset %d), %d episodes, survival %.0f%%, goal %.0f%%, "
                 "agreement %.1f%%, loss %.3f, train accuracy %.1f%%", it, row.collected, row.dataset,
                 n_ep, row.survival, row.goal, row.agreement, loss, acc)
        _write_log(out_dir, logs)
        save_qnet(out_dir / "checkpoints" / f"iteration_{it}.pt", net, env_cfg,  # type: ignore[arg-type]
                  {"dagger": {"iterations": it + 1, "dataset": len(data)}})
    save_qnet(out_dir / "checkpoints" / "final.pt", net, env_cfg,  # type: ignore[arg-type]
              {"dagger": {"iterations": len(logs), "dataset": len(data)}})
    summary = {"kind": "dagger", "iterations": len(logs), "dataset": len(data),
               "env_steps": sum(r.collected for r in logs), "wall_s": round(time.perf_counter() - start, 3),
               "loss": "cross_entropy", "last": asdict(logs[-1]) if logs else None}
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    return logs


def _write_log(out_dir: Path, logs: list[IterationLog]) -> None:
    import csv

    out_dir.mkdir(parents=True, exist_ok=True)
    with (out_dir / "dagger.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, list(asdict(logs[0])))
        w.writeheader()
        w.writerows({k: round(v, 4) if isinstance(v, float) else v for k, v in asdict(r).items()}
                    for r in logs)
