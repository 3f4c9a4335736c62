"""The training loop of all three modes, with episode-aligned checkpoints for exact resume.

Collection runs in this process, episode by episode, through the TorchRL env and policy
modules; every ``train_every`` env steps the learner does ``updates_per_round`` updates. Each
episode resets with a seed derived from (run seed, episode index), and checkpoints are taken
between episodes with every RNG state, so a resumed run repeats exactly what the killed run
would have done after its last checkpoint.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import logging
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from tensordict.nn import TensorDictSequential
from torchrl.envs.utils import step_mdp
from tqdm import tqdm

from memrl.checkpoint import load_qnet, save_qnet
from memrl.data.buffers import PriorKnowledgeBuffer, agent_buffer, demo_buffer
from memrl.data.transitions import to_transitions
from memrl.dqn import checkpoint as ckpt
from memrl.dqn.learner import Learner, make_exploration
from memrl.dqn.records import RunRecords
from memrl.dqn.stage1 import (
    Stage1Progress,
    agreement,
    agreement_parts,
    drive_check,
    split_demos,
    stop_reason,
)
from memrl.envs.torchrl_env import make_env
from memrl.envs.vehicles import N_ACTIONS
from memrl.evaluation.periodic import PeriodicEvaluation

log = logging.getLogger(__name__)


@dataclass
class Counters:
    """Progress of a run (saved in checkpoints)."""

    frames: int = 0
    episodes: int = 0
    updates: int = 0
    update_rows: int = 0
    stage: str = "default"
    """default | A | B1 (prior knowledge only) | B2 (plain double DQN from B1's weights)."""


@dataclass
class Summary:
    """What ``train`` returns and writes to ``summary.json``."""

    run_dir: str
    mode: str
    seed: int
    frames: int
    episodes: int
    updates: int
    stage: str
    mean_return_last_20: float
    mean_survival_last_20: float
    reached_target_last_20: float
    stage1: dict[str, Any]
    wall_s: float
    updates_per_s: float
    frames_per_s: float
    learner_busy: float
    """Share of wall time spent in learner updates (sampling included)."""
    resumed_from_episode: int | None


@dataclass
class _Episode:
    """Running totals of the episode under way."""

    ret: float = 0.0
    length: int = 0
    collided: bool = False
    reached: bool = False
    done: bool = False


def episode_seed(seed: int, episode: int) -> int:
    """Reset seed of an episode: fixed by the run seed and the episode index."""
    return int(np.random.SeedSequence([int(seed), int(episode)]).generate_state(1)[0])


class Trainer:
    """One run of Default, mode A or mode B (both stages)."""

    def __init__(self, cfg: DictConfig, out_dir: Path, demos: TensorDictBase | None = None,
                 logger: Any | None = None) -> None:
        self.cfg, self.out_dir = cfg, out_dir
        self.mode = cfg.mode.name
        if cfg.agent.threads:
            torch.set_num_threads(int(cfg.agent.threads))
        torch.manual_seed(int(cfg.seed))
        np.random.seed(int(cfg.seed) % 2**32)
        self.env = make_env(cfg.env)
        if cfg.self_play_every and self._learned_controller() is None:
            raise ValueError("config 'self_play_every': snapshots join the learned cars' pool; "
                             "it needs opponent=learned or opponent=mixed")
        self.learner = Learner(cfg.agent)
        self.counters = Counters(stage={"default": "default", "A": "A", "B": "B1"}[self.mode])
        self.stage1 = Stage1Progress()
        self._stage1_best: dict[str, torch.Tensor] | None = None
        """Stage 1 with drive episodes: the loss module's weights that drove best so far."""
        self.demos = demos
        if self.mode in ("A", "B") and demos is None:
            raise ValueError(f"mode {self.mode} needs prior knowledge (demos)")
        self.records = RunRecords(out_dir, logger, echo=not cfg.progress)
        self.periodic = PeriodicEvaluation(cfg.get("eval"), cfg.env, out_dir, self.records.log)
        self._build_stage()
        self._acc: dict[str, list[float]] = {"loss": [], "demo": []}
        self._recent: deque[dict[str, Any]] = deque(maxlen=20)
        self._update_time = 0.0
        self._losses: deque[float] = deque(maxlen=100_000)
        self.resumed_from: int | None = None
        self._pool: ThreadPoolExecutor | None = None

    # ------------------------------------------------------------------ construction
    def _build_stage(self) -> None:
        """Buffer and exploration of the current stage."""
        a, m = self.cfg.agent, self.cfg.mode
        capacity, batch = int(self.cfg.buffer.capacity), int(a.batch_size)
        compact = bool(self.cfg.buffer.get("compact", True))  # each frame stored once
        eps = (m.stage2.eps_start, m.stage2.eps_end, m.stage2.eps_decay_frames) \
            if self.counters.stage == "B2" else (a.eps_start, a.eps_end, a.eps_decay_frames)
        self.explore = make_exploration(*eps)
        # Overlap mode acts with a copy of the online network, refreshed after each round, so
        # the collecting thread never reads weights the optimizer is writing.
        actor = self.learner.actor
        self._acting_net: torch.nn.Module | None = None
        if bool(a.get("overlap", False)):
            actor = copy.deepcopy(self.learner.actor)
            for module in actor.modules():  # a copied compiled forward would call the original
                module._compiled_call_impl = None
            self._acting_net = actor
        self.acting = TensorDictSequential(actor, self.explore)
        self.held_out: TensorDictBase | None = None
        if self.counters.stage == "A":
            assert self.demos is not None
            self.buffer: Any = PriorKnowledgeBuffer(self.demos, capacity, float(m.demo_fraction),
                                                    batch, sampling=str(m.sampling),
                                                    compact=compact)
        elif self.counters.stage == "B1":
            assert self.demos is not None
            self.learner.margin_weight = float(m.stage1.margin_weight)
            self.learner.margin = float(m.stage1.margin)
            if m.stage1.lr is not None:  # a resumed run gets the same from the optimizer state
                self.learner.set_lr(float(m.stage1.lr))
            train, self.held_out = split_demos(self.demos, float(m.stage1.holdout_fraction),
                                               int(self.cfg.seed))
            self.buffer = demo_buffer(train, batch, compact=compact)
        else:
            self.buffer = agent_buffer(capacity, batch, compact=compact)

    # ------------------------------------------------------------------ checkpoints
    def _state(self) -> dict[str, Any]:
        return {
            "config": ckpt.comparable(self.cfg),
            "counters": dataclasses.asdict(self.counters),
            "stage1": dataclasses.asdict(self.stage1),
            "learner": self.learner.state_dict(),
            "explore": self.explore.state_dict(),
            "acc": self._acc,
            "recent": list(self._recent),
            "rng": ckpt.rng_state(),
            "stage1_best": self._stage1_best,
        }

    def save_checkpoint(self) -> None:
        agent_data = self.counters.stage in ("default", "A", "B2") and len(self.buffer) > 0
        ckpt.save(self.out_dir / "checkpoints" / "last", self._state(),
                  self.buffer if agent_data else None)
        self.records.flush()  # the logger gets its points once a checkpoint covers them

    def resume(self, run_dir: Path) -> None:
        """Continue from the last complete checkpoint of ``run_dir`` (same config required)."""
        where = ckpt.find(run_dir)
        state = ckpt.load_state(where, self.cfg)
        self.counters = Counters(**state["counters"])
        self.stage1 = Stage1Progress(**state["stage1"])
        self._stage1_best = state.get("stage1_best")
        self.learner.load_state_dict(state["learner"])
        self._build_stage()
        self.explore.load_state_dict(state["explore"])
        if (where / "buffer").exists():
            try:
                self.buffer.loads(where / "buffer")
            except (OSError, ValueError, RuntimeError, KeyError) as err:  # a checkpoint without manifest
                raise ckpt.CheckpointError(f"{where / 'buffer'}: unreadable replay buffer "
                                           f"({type(err).__name__}: {err})") from err
        self._acc = state["acc"]
        self._recent = deque(state["recent"], maxlen=20)
        ckpt.set_rng_state(state["rng"])
        self.records.rewind(self.counters.episodes, self.counters.update_rows)
        self.periodic.rewind(self.counters.episodes)
        self._restore_pool()
        self.resumed_from = self.counters.episodes
        log.info("resumed %s at stage %s: %d episodes, %d frames, %d updates", where,
                 self.counters.stage, self.counters.episodes, self.counters.frames,
                 self.counters.updates)

    # ------------------------------------------------------------------ learning
    def _learn(self) -> None:
        t0 = time.perf_counter()
        batch = self.buffer.sample()
        loss = self.learner.update(batch)
        self._update_time += time.perf_counter() - t0
        self._book(batch, loss)

    def _book(self, batch: TensorDictBase, loss: float) -> None:
        """Counters, accumulators and the periodic updates.csv row of one finished update."""
        self.counters.updates += 1
        self._acc["loss"].append(loss)
        self._acc["demo"].append(float(batch["is_demo"].sum()))
        self._losses.append(loss)
        self._last_batch = batch
        if self.counters.updates % int(self.cfg.log_every) == 0:
            self._log_updates()

    def _log_updates(self) -> None:
        """One row of updates.csv over the updates since the last row."""
        c, demo, batch = self.counters, self._acc["demo"], self._last_batch
        if not demo:
            return
        wall = max(time.perf_counter() - self._t_start, 1e-9)
        self.records.update({
            "updates": c.updates, "env_steps": c.frames, "stage": c.stage,
            "loss": float(np.mean(self._acc["loss"])),
            "mean_q": float(self.learner.q_values(batch["pixels"]).mean()),
            "demo_share": float(np.mean(demo)) / len(batch),
            "demo_count_min": int(min(demo)), "demo_count_max": int(max(demo)),
            "updates_per_s": (c.updates - self._updates0) / wall,
            "frames_per_s": (c.frames - self._frames0) / wall,
            "epsilon": float(self.explore.eps),
        })
        c.update_rows += 1
        self._acc = {"loss": [], "demo": []}

    def run_stage1(self, after_update: Callable[[int], None] | None = None) -> None:
        """Mode B stage 1 on the demo-only buffer, then the switch to stage 2.

        ``after_update(updates)``, when given, is called after each update, before the check
        and the switch (the stage-1 bench drives the greedy agent from it every N updates).
        """
        s1, cfg = self.stage1, self.cfg.mode.stage1
        assert self.held_out is not None
        while not s1.done:
            self._learn()
            s1.updates += 1
            if after_update is not None:
                after_update(s1.updates)
            if s1.updates % int(cfg.check_every) == 0 or s1.updates >= int(cfg.max_updates):
                s1.losses.append(float(np.mean(list(self._losses)[-int(cfg.check_every):])))
                s1.agreements.append(agreement(self.learner.qnet, self.held_out))
                s1.parts.append(agreement_parts(self.learner.qnet, self.held_out))
                if int(cfg.drive_episodes) > 0:
                    self._drive_stage1()
                s1.stop_reason = stop_reason(cfg, s1)
                log.info("stage 1: %d updates, loss %.4f, agreement %.3f (%s)%s", s1.updates,
                         s1.losses[-1], s1.agreements[-1],
                         ", ".join(f"{k} {v:.3f}" for k, v in s1.parts[-1].items()),
                         f" -> stop: {s1.stop_reason}" if s1.stop_reason else "")
                self._log_updates()  # every check gets its row
                self.records.stage1_check(s1.updates, self._stage1_metrics())
                if s1.stop_reason:
                    self._finish_stage1()
                self.save_checkpoint()

    def _stage1_metrics(self) -> dict[str, float]:
        """Logger values of the stage-1 check just made."""
        s1 = self.stage1
        drove = bool(s1.drives) and s1.drives[-1]["updates"] == s1.updates
        return {"check_loss": s1.losses[-1], "agreement": s1.agreements[-1],
                **{f"agreement_{k}": v for k, v in s1.parts[-1].items()},
                **({f"drive_{k}": s1.drives[-1][k] for k in ("survived", "reached", "both")}
                   if drove else {})}

    def _drive_stage1(self) -> None:
        """Stage 1's behaviour check: drive the greedy agent; remember the best weights."""
        s1, cfg = self.stage1, self.cfg.mode.stage1
        start = time.perf_counter()
        counts = drive_check(self.learner.qnet, self.cfg.env, int(cfg.drive_episodes),
                             int(cfg.drive_seed))
        s1.drive_s += time.perf_counter() - start
        s1.drives.append({"updates": s1.updates, **counts})
        best = next((d["both"] for d in s1.drives if d["updates"] == s1.best_updates), -1)
        if bool(cfg.keep_best) and counts["both"] >= best:
            s1.best_updates = s1.updates
            self._stage1_best = {k: v.detach().clone()
                                 for k, v in self.learner.loss_module.state_dict().items()}
        log.info("stage 1: %d updates, drive: %d/%d survived, %d reached, %d both (best at %d)",
                 s1.updates, counts["survived"], int(cfg.drive_episodes), counts["reached"],
                 counts["both"], s1.best_updates)

    def _finish_stage1(self) -> None:
        self.stage1.done = True
        if self._stage1_best is not None and self.stage1.best_updates != self.stage1.updates:
            self.learner.loss_module.load_state_dict(self._stage1_best)
            self.stage1.stop_reason += f"; weights of update {self.stage1.best_updates} (drove best)"
        self._stage1_best = None
        path = self.out_dir / "checkpoints" / "stage1.pt"
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save({"loss_module": self.learner.loss_module.state_dict(),
                    "stage1": dataclasses.asdict(self.stage1)}, path)
        # Stage 2 starts from the stage-1 weights for both online and target networks.
        weights = torch.load(path, weights_only=False)["loss_module"]
        self.learner.loss_module.load_state_dict(weights)
        self.learner.sync_target()
        self.learner.reset_optimizer()
        self.counters.stage = "B2"
        self.learner.margin_weight = 0.0  # stage 2 trains as Default
        self._build_stage()
        log.info("stage 1 done (%s); stage 2 from %s", self.stage1.stop_reason, path)

    # ------------------------------------------------------------------ self-play
    def _learned_controller(self) -> Any | None:
        from memrl.envs.torchrl_env import unwrap

        opponents = unwrap(self.env)._opponents
        return next((c for c in opponents.controllers if c.kind == "learned"), None) \
            if opponents is not None else None

    def _snapshot_to_pool(self) -> None:
        """Add the current agent to the learned cars' pool (``self_play_every`` episodes)."""
        path = self.out_dir / "pool" / f"episode_{self.counters.episodes:07d}.pt"
        save_qnet(path, self.learner.qnet,
                  OmegaConf.to_container(self.cfg.env, resolve=True))  # type: ignore[arg-type]
        controller = self._learned_controller()
        assert controller is not None  # checked at start
        controller.add_network(load_qnet(path)[0])

    def _restore_pool(self) -> None:
        """After a resume: the snapshots taken up to the checkpoint rejoin the pool, in order."""
        every = int(self.cfg.self_play_every or 0)
        for n in range(every, self.counters.episodes + 1, every) if every else []:
            path = self.out_dir / "pool" / f"episode_{n:07d}.pt"
            self._learned_controller().add_network(load_qnet(path)[0])  # type: ignore[union-attr]

    def _act_step(self, td: TensorDictBase, ep: _Episode) -> TensorDictBase:
        """One env step with the acting policy; returns the transition, counted in ``ep``."""
        c = self.counters
        if c.frames < int(self.cfg.agent.warmup_frames):
            td["action"] = torch.randint(N_ACTIONS, ())
        else:
            self.acting(td)
            self.explore.step(1)
        td = self.env.step(td)
        nxt = td["next"]
        ep.ret += float(nxt["reward"])
        ep.length += 1
        ep.collided = ep.collided or bool(nxt["collided"])
        ep.reached = ep.reached or bool(nxt["reached_target"])
        ep.done = bool(nxt["done"])
        c.frames += 1
        return td

    def _collect(self, td: TensorDictBase, steps: int, ep: _Episode,
                 out: list[TensorDictBase]) -> TensorDictBase:
        """Up to ``steps`` env steps (fewer if the episode ends); transitions go to ``out``.
        Returns the tensordict to act on next (the last transition once the episode is done)."""
        for _ in range(steps):
            td = self._act_step(td, ep)
            out.append(to_transitions(td.unsqueeze(0)))
            if ep.done:
                return td
            td = step_mdp(td)
        return td

    def _learn_due(self) -> bool:
        a, frames = self.cfg.agent, self.counters.frames
        return frames >= int(a.warmup_frames) and frames % int(a.train_every) == 0

    def _overlapped_round(self, td: TensorDictBase, ep: _Episode) -> TensorDictBase:
        """One update round in a thread while this one collects the next ``train_every`` steps.

        Hand-written: TorchRL's collectors run free of the update schedule (no exact resume);
        here the batches are drawn first, the thread only steps the env with the acting copy,
        and its transitions join the buffer after the update, so the run stays deterministic.
        """
        a = self.cfg.agent
        batches = [self.buffer.sample() for _ in range(int(a.updates_per_round))]
        new: list[TensorDictBase] = []

        def learn() -> tuple[list[float], float]:
            t0 = time.perf_counter()
            losses = [self.learner.update(batch) for batch in batches]
            return losses, time.perf_counter() - t0

        # The update runs in the learner thread and the env in this one: every draw from the
        # global RNGs (exploration, env) stays in one thread, in a fixed order.
        future = self._learner_thread().submit(learn)
        try:
            td = self._collect(td, int(a.train_every), ep, new)
        finally:
            losses, seconds = future.result()  # re-raises the update's error, if any
        self._update_time += seconds
        for batch, loss in zip(batches, losses, strict=True):
            self._book(batch, loss)
        for transition in new:
            self.buffer.extend(transition)
        self._sync_acting()
        return td

    def _learner_thread(self) -> ThreadPoolExecutor:
        """The one long-lived learner thread of overlap mode, with ``agent.threads`` torch
        threads of its own (a new thread would otherwise start with one per core)."""
        if self._pool is None:
            threads = int(self.cfg.agent.threads)

            def init() -> None:
                if threads:
                    torch.set_num_threads(threads)

            self._pool = ThreadPoolExecutor(1, thread_name_prefix="memrl-learn", initializer=init)
        return self._pool

    def close(self) -> None:
        """Stop the learner thread (overlap mode); the trainer can go on and restart it."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def _sync_acting(self) -> None:
        """Refresh the acting copy from the online network (overlap mode)."""
        if self._acting_net is not None:
            with torch.no_grad():
                for dst, src in zip(self._acting_net.parameters(), self.learner.qnet.parameters(),
                                    strict=True):
                    dst.copy_(src)

    def run_episode(self) -> None:
        """One episode of collection with interleaved (or, with ``agent.overlap``, overlapped)
        updates."""
        cfg, c = self.cfg, self.counters
        td = self.env.reset(seed=episode_seed(int(cfg.seed), c.episodes))
        ep = _Episode()
        overlap = bool(cfg.agent.get("overlap", False))
        while not ep.done:
            new: list[TensorDictBase] = []
            td = self._collect(td, 1, ep, new)
            self.buffer.extend(new[0])
            while self._learn_due():
                if overlap and not ep.done:
                    td = self._overlapped_round(td, ep)  # ends on a due frame unless done
                    continue
                for _ in range(int(cfg.agent.updates_per_round)):
                    self._learn()
                self._sync_acting()
                break
        c.episodes += 1
        row = {"episode": c.episodes, "env_steps": c.frames, "return": round(ep.ret, 4),
               "survival_steps": ep.length, "length": ep.length, "collided": int(ep.collided),
               "reached_target": int(ep.reached), "epsilon": round(float(self.explore.eps), 5),
               "stage": c.stage}
        self.records.episode(row)
        self._recent.append(row)
        every = int(self.cfg.self_play_every or 0)
        if every and c.episodes % every == 0:
            self._snapshot_to_pool()
        self.periodic.after_episode(self.learner.qnet, c.episodes, c.frames)

    # ------------------------------------------------------------------ driver
    def _budget_left(self) -> bool:
        c, cfg = self.counters, self.cfg
        frames_done = cfg.total_frames is not None and c.frames >= int(cfg.total_frames)
        episodes_done = cfg.total_episodes is not None and c.episodes >= int(cfg.total_episodes)
        return not (frames_done or episodes_done)

    def run(self) -> Summary:
        cfg, c = self.cfg, self.counters
        self._t_start = time.perf_counter()
        self._frames0, self._updates0 = c.frames, c.updates
        if c.stage == "B1":
            self.run_stage1()
        total = cfg.total_episodes if cfg.total_episodes is not None else cfg.total_frames
        unit = "episodes" if cfg.total_episodes is not None else "frames"
        bar = tqdm(total=int(total), initial=c.episodes if unit == "episodes" else c.frames,
                   desc=f"train {self.mode}", unit=unit, disable=not cfg.progress,
                   dynamic_ncols=True)
        try:
            while self._budget_left():
                before = c.frames
                self.run_episode()
                bar.update(1 if unit == "episodes" else c.frames - before)
                bar.set_postfix(frames=c.frames, episodes=c.episodes,
                                eps=f"{float(self.explore.eps):.2f}",
                                ret=f"{np.mean([r['return'] for r in self._recent]):.1f}")
                if c.episodes % int(cfg.checkpoint_every) == 0:
                    self.save_checkpoint()
        finally:
            self.close()
            bar.close()
        self.save_checkpoint()
        return self._summary()

    def _summary(self) -> Summary:
        c, wall = self.counters, time.perf_counter() - self._t_start
        recent = list(self._recent)

        def mean(key: str) -> float:
            return float(np.mean([float(r[key]) for r in recent])) if recent else float("nan")

        summary = Summary(
            run_dir=str(self.out_dir), mode=self.mode, seed=int(self.cfg.seed), frames=c.frames,
            episodes=c.episodes, updates=c.updates, stage=c.stage,
            mean_return_last_20=mean("return"), mean_survival_last_20=mean("survival_steps"),
            reached_target_last_20=mean("reached_target"),
            stage1=dataclasses.asdict(self.stage1), wall_s=wall,
            updates_per_s=(c.updates - self._updates0) / max(wall, 1e-9),
            frames_per_s=(c.frames - self._frames0) / max(wall, 1e-9),
            learner_busy=self._update_time / max(wall, 1e-9),
            resumed_from_episode=self.resumed_from)
        save_qnet(self.out_dir / "checkpoints" / "final.pt", self.learner.qnet,
                  OmegaConf.to_container(self.cfg.env, resolve=True),  # type: ignore[arg-type]
                  {"summary": dataclasses.asdict(summary)})
        (self.out_dir / "summary.json").write_text(json.dumps(dataclasses.asdict(summary), indent=2))
        return summary
