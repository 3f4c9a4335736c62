"""The training loop of all three modes: N envs, any device, exact resume.

:meth:`Trainer.run` is the whole algorithm, one :meth:`Trainer.iterate` after another: sample
the update rounds that are due, run them (in a learner thread while the next env steps are
collected, with ``agent.overlap``), store the new transitions, book finished episodes,
checkpoint (:mod:`memrl.dqn.seed_group` takes the turns of several runs in one process). The
pieces it calls each live in their own module: the stages' buffers, exploration and losses
(:mod:`memrl.dqn.builder`), collection (:mod:`memrl.dqn.collector`), the replay ratio and
budgets (:mod:`memrl.dqn.schedule`), overlapped rounds (:mod:`memrl.dqn.overlap`), an offline
stage's stop rule (:mod:`memrl.dqn.stage1`), the self-play pool (:mod:`memrl.dqn.self_play`),
run records (:mod:`memrl.dqn.records`).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections import deque
from collections.abc import Callable, Generator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from tensordict.nn import TensorDictSequential
from tqdm import tqdm

from memrl.checkpoint import load_stage1_qnet, offline_state, save_offline, save_qnet, stage1_source
from memrl.checkpoint import resume as ckpt
from memrl.checkpoint.weights import load_weights
from memrl.data.buffers import priority_sampler
from memrl.data.priority_sampler import reprioritize
from memrl.dqn.builder import Stage, StageInputs, build_stage
from memrl.dqn.collector import Collector, EpisodeEnd, Steps, drive
from memrl.dqn.learner import Learner
from memrl.dqn.overlap import RoundRunner
from memrl.dqn.records import RunRecords
from memrl.dqn.schedule import Budget, UpdateSchedule
from memrl.dqn.self_play import SelfPlayPool
from memrl.dqn.stage1 import Stage1Checks, Stage1Progress
from memrl.dqn.teacher import Teacher
from memrl.envs.batched import resolve_device
from memrl.envs.vehicles import N_ACTIONS
from memrl.evaluation.periodic import PeriodicEvaluation
from memrl.modes import mode_of
from memrl.modules.qnet import network_for_task
from memrl.modules.risk import TASK_ACTION_KEY, proposes, with_task_action
from memrl.progress import drawn, progress_bar
from memrl.stop import raise_pending, stop_requested

log = logging.getLogger(__name__)


@dataclass
class Counters:
    """Progress of a run (saved in checkpoints)."""

    frames: int = 0
    """Env steps, summed over envs."""
    episodes: int = 0
    updates: int = 0
    rounds: int = 0
    """Update rounds of the env stages taken so far (see :class:`UpdateSchedule`)."""
    update_rows: int = 0
    stage: str = "default"
    """The current stage's name (:mod:`memrl.modes`: default | A | B1 | B2 | ...)."""


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
    """Wall time of this call (the rates below are over it)."""
    updates_per_s: float
    frames_per_s: float
    learner_busy: float
    """Share of wall time spent in learner updates (sampling excluded)."""
    resumed_from_episode: int | None
    num_envs: int = 1
    device: str = "cpu"
    train_wall_s: float | None = None
    """Wall time of the whole run over all its calls: each killed call counts up to its last
    checkpoint. None when it resumed from a checkpoint made before this was recorded."""


class Trainer:
    """One run of any mode (:mod:`memrl.modes`: its stages in turn, an offline one first where it
    has one), on ``env.num_envs`` envs."""

    def __init__(self, cfg: DictConfig, out_dir: Path, demos: TensorDictBase | None = None,
                 logger: Any | None = None, engine: Any | None = None) -> None:
        self.cfg, self.out_dir, self.demos = cfg, out_dir, demos
        self.spec = mode_of(cfg)
        self.mode = self.spec.name
        if self.spec.needs_demos and demos is None:
            raise ValueError(f"mode {self.mode} needs prior knowledge (demos)")
        if cfg.agent.threads:
            torch.set_num_threads(int(cfg.agent.threads))
        torch.manual_seed(int(cfg.seed))
        np.random.seed(int(cfg.seed) % 2**32)
        self.device = resolve_device(cfg.device)
        self.num_envs = int(cfg.env.num_envs)
        # engine: this run's slice of a shared engine (memrl.envs.shared_engine), else its own
        self.collector = Collector(cfg.env, self.num_envs, self.device, int(cfg.seed), engine)
        network = network_for_task(cfg.network, cfg.env, float(cfg.agent.gamma))  # e.g. a support's bounds
        self.learner = Learner(cfg.agent, self.device, seed=int(cfg.seed), network=network)
        self.proposes = proposes(self.learner.qnet)
        """The task head learns from its proposals: every stored transition has ``task_action``."""
        if self.proposes and demos is not None:
            self.demos = with_task_action(demos)
        self.rounds = RoundRunner(self.learner, bool(cfg.agent.overlap),
                                  int(cfg.agent.threads))
        self.schedule = UpdateSchedule(int(cfg.agent.train_every), max(int(cfg.agent.warmup_frames),
                                                                       self._warm_start()))
        self.budget = Budget(cfg.total_frames, cfg.total_episodes)
        self.self_play = SelfPlayPool(int(cfg.self_play_every or 0),
                                      self.collector.learned_controller(), out_dir, cfg.env)
        self.records = RunRecords(out_dir, logger, echo=not drawn(cfg.progress))
        self.periodic = PeriodicEvaluation(cfg.eval, cfg.env, out_dir, self.records.log)
        self.counters = Counters(stage=self.spec.stages[0].name)
        self.weights_dir = out_dir / "checkpoints"
        """Where the run's stage-1 weights are (a stage's teacher): this run's, or the resumed run's."""
        self.offline_progress = Stage1Progress()
        self._set_stage(self.counters.stage)
        self._acc: dict[str, list[float]] = {"loss": [], "demo": []}
        self._recent: deque[dict[str, Any]] = deque(maxlen=20)
        self._losses: deque[float] = deque(maxlen=100_000)
        self._pending: list[tuple[torch.Tensor, torch.Tensor]] = []  # (loss, demo count) not read back yet
        self._readback_every = int(cfg.agent.loss_readback)
        self._checkpointed_at = 0  # episodes at the last checkpoint
        self.resumed_from: int | None = None
        self.stopped_saved = False
        """The loop stopped on request after writing its checkpoint (:meth:`iterate`)."""
        self._wall_before: float | None = 0.0  # training seconds of earlier calls (None: unknown)
        self._bar: tqdm | None = None  # begin() opens it
        self._start_clock()  # run() starts it again; stage 1 alone (bench, tests) counts from here

    # ------------------------------------------------------------------ the loop
    def run(self) -> Summary:
        try:
            self.begin()
            while not self.done():
                self.iterate()
            self.end_rounds()
        finally:
            self.close()
        return self.finish()

    def begin(self) -> None:
        """The clock, the progress bar and the offline stage (where the mode has one)."""
        self._start_clock()
        self._bar = self._progress_bar()
        if self.stage.offline:
            self.run_offline()

    def done(self) -> bool:
        """The budget is spent (N = 1: and the episode is over)."""
        return self._budget_done()

    def iterate(self) -> None:
        """One turn of the loop: the update rounds due, the env steps until the next is due."""
        drive(self.iterate_steps())

    def iterate_steps(self) -> Generator[torch.Tensor, None, None]:
        """:meth:`iterate`, pausing before each env step with its actions (a shared engine steps
        every run's envs there: :func:`memrl.dqn.seed_group.run_lockstep`)."""
        c = self.counters
        batches = self._due_batches()  # sampled now, before the new steps join
        self.rounds.start(batches)  # overlapped with the steps, or before them
        try:
            steps = yield from self._collect_steps()
        finally:
            losses = self.rounds.finish()
        self._book(batches, losses)
        self._reprioritize(batches)  # prioritized replay: the new TD errors
        for part in steps.transitions:
            self.stage.buffer.extend(part)
        self._episodes_done(steps.episodes)
        self.periodic.after_steps(self.learner.qnet, c.episodes, c.frames)
        if self.teacher is not None and self.teacher.after_steps(self.learner.qnet, c.frames):
            self._teach()
        assert self._bar is not None, "begin() first"
        self._bar.update(len(steps.episodes) if self.budget.total_episodes is not None else steps.frames)
        if c.episodes // self._ckpt_every > self._checkpointed_at // self._ckpt_every:
            self.save_checkpoint()
        if stop_requested() and self.can_stop():
            self.save_checkpoint()  # SIGINT / SIGTERM: a resumable stop (memrl.stop)
            self.stopped_saved = True
            raise_pending()

    def can_stop(self) -> bool:
        """A checkpoint now resumes exactly (N = 1: only between episodes)."""
        return self.num_envs > 1 or self.collector.between_episodes()

    def end_rounds(self) -> None:
        """The update rounds the last steps made due."""
        batches = self._due_batches()
        self._book(batches, self.rounds.flush(batches))
        self._reprioritize(batches)

    def close(self) -> None:
        """The learner thread and the progress bar (also after a failed or stopped turn)."""
        self.rounds.close()
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def finish(self) -> Summary:
        """The final checkpoint and the summary."""
        self.save_checkpoint()
        return self._summary()

    def run_offline(self, after_update: Callable[[int], None] | None = None) -> None:
        """The offline stage (mode B's stage 1) on prior knowledge alone until its stop rule
        stops it, then the switch to the next stage.

        ``after_update(updates)``, when given, is called after each update, before the check
        and the switch (the stage-1 bench drives the greedy agent from it every N updates).
        """
        checks, p = self.offline_checks, self.offline_progress
        assert checks is not None
        if (init := self._offline_settings.init) is not None:
            self._offline_from(stage1_source(str(init), self.cfg.env))
            return
        while not p.done:
            batch = self.stage.buffer.sample()
            self._book([batch], [self.learner.step(batch)])
            p.updates += 1
            if after_update is not None:
                after_update(p.updates)
            if checks.due():
                self._read_back()
                recent = list(self._losses)[-int(self._offline_settings.check_every):]
                metrics = checks.check(self.learner.qnet, self.learner.loss_module, recent)
                self._log_updates()  # every check gets its row
                self.records.stage1_check(p.updates, metrics)
                if p.stop_reason:
                    self._finish_offline()
                self.save_checkpoint()
                if stop_requested():  # stage 1 stops at its next checkpoint
                    raise_pending()

    # ------------------------------------------------------------------ steps of the loop
    def _due_batches(self) -> list[TensorDictBase]:
        """One batch per update of the rounds due now (none during warm-up)."""
        c = self.counters
        due = self.schedule.rounds_due(c.frames) - c.rounds
        c.rounds += due
        return [self.stage.buffer.sample() for _ in range(due * self.stage.updates_per_round)]

    def _collect_steps(self) -> Generator[torch.Tensor, None, Steps]:
        """Env steps until the next round is due (or the frame budget ends; N = 1: or the
        episode ends, where budgets and checkpoints are checked)."""
        c, n = self.counters, self.num_envs
        steps = self.schedule.steps_to_next_round(c.frames, c.rounds, n)
        left = self.budget.steps_left(c.frames, n)
        if n > 1 and left is not None:
            steps = min(steps, left)
        out = yield from self.collector.collect_steps(self._act, steps, c.frames, stop_at_episode_end=n == 1)
        c.frames += out.frames
        return out

    @torch.no_grad()
    def _act(self, td: TensorDictBase, frames: int) -> None:
        """Random actions during warm-up (a teacher's warm start: its own), then the acting
        network with epsilon-greedy (a teacher's roll-ins: its actions first)."""
        teacher = self.teacher
        if teacher is not None and teacher.warming(frames):
            teacher.act_warm(td, self.stage.explore)
        elif frames < self.schedule.warmup_frames:
            td["action"] = torch.randint(N_ACTIONS, td.shape, device=td.device)
        else:
            assert self.acting is not None and self.stage.explore is not None
            self.acting(td)
            if self.proposes:  # before a roll-in: its guided steps are the teacher's, as executed
                td[TASK_ACTION_KEY] = self._proposals(td)
            self.stage.explore.step(self.num_envs)
            if teacher is not None:
                teacher.roll_in(td, self.collector.length)
            return
        if self.proposes:  # random and warm-start steps: what was executed was proposed
            td[TASK_ACTION_KEY] = td["action"].clone()

    def _proposals(self, td: TensorDictBase) -> torch.Tensor:
        """The task head's proposals: the exploration's draws of this step applied to the task
        head's own greedy action (the acting network's ``base``, before the critic's mask)."""
        net = self.rounds.acting_net.module[0].module.net  # QValueActor -> Decision -> the risk network
        greedy = net.base(td["pixels"]).argmax(-1)
        return self.stage.explore.propose(greedy.reshape(td["action"].shape))

    def _episodes_done(self, ends: list[EpisodeEnd]) -> None:
        """Rows, self-play snapshots and periodic evaluations of finished episodes."""
        c, eps = self.counters, self._epsilon()
        for e in ends:
            c.episodes += 1
            row = {"episode": c.episodes, "env_steps": e.frames, "return": round(e.ret, 4),
                   "survival_steps": e.length, "length": e.length, "collided": int(e.collided),
                   "reached_target": int(e.reached), "epsilon": round(eps, 5), "stage": c.stage}
            self.records.episode(row)
            self._recent.append(row)
            self.self_play.after_episode(c.episodes, self.learner.qnet)
            self.periodic.after_episode(self.learner.qnet, c.episodes, e.frames)

    def _budget_done(self) -> bool:
        c = self.counters
        # N = 1: budgets are checked between episodes (the reference env keeps no mid-episode
        # checkpoint); N > 1: after any step.
        return self.budget.done(c.frames, c.episodes) and (
            self.num_envs > 1 or self.collector.between_episodes())

    # ------------------------------------------------------------------ stages
    def _set_stage(self, name: str, fresh_optimizer: bool = False) -> None:
        """Build stage ``name``: its buffer, exploration and acting policy; start the learner
        on its loss terms (and a fresh optimizer when it begins a new optimisation)."""
        self.counters.stage = name
        self.stage: Stage = build_stage(self.spec.stage(name), StageInputs.of(self.cfg), self.demos,
                                        self.num_envs, self.device)
        self.learner.start_stage(self.stage.terms, self.stage.lr, fresh_optimizer)
        self.offline_checks = Stage1Checks(self._offline_settings, self.cfg.env, self.stage.held_out,
                                           self.offline_progress) if self.stage.offline else None
        self.acting: TensorDictSequential | None = None if self.stage.offline else TensorDictSequential(
            self.rounds.acting_net, self.stage.explore)
        self.teacher = self._teacher_of(self.stage)
        self._teach()

    def _teach(self) -> None:
        """The learner's distillation sees the stage's teacher and its schedule's current scale."""
        self.learner.teacher = None if self.teacher is None else self.teacher.net
        self.learner.teacher_scale = 0.0 if self.teacher is None else self.teacher.state.scale

    def _teacher_of(self, stage: Stage) -> Teacher | None:
        """The online stage's teacher (:mod:`memrl.dqn.teacher`): the run's own stage-1 weights,
        frozen; None for a stage without one."""
        settings = stage.spec.teacher(self.cfg.mode)
        if settings is None or stage.offline:
            return None
        net = load_stage1_qnet(self.weights_dir)
        return Teacher(settings, net, self.cfg.env, self.num_envs, int(self.cfg.seed), self.device,
                       self.out_dir)

    def _warm_start(self) -> int:
        """Env steps of the online stage's teacher warm start (0: none); its updates start after them."""
        online = [s.teacher(self.cfg.mode) for s in self.spec.stages if not s.offline]
        return max((int(t.warm_start) for t in online if t is not None), default=0)

    @property
    def _offline_settings(self) -> Any:
        """The ``mode`` node of the current offline stage's stop rule (``mode.stage1``)."""
        return self.cfg.mode[self.stage.spec.settings]

    def _offline_from(self, file: Path) -> None:
        """The offline stage done by another run (``mode.stage1.init``): its weights and record,
        then the switch."""
        state = load_weights(file, "stage-1 weights")  # checked again: read once more here
        self.learner.loss_module.load_state_dict(
            offline_state(state, self.learner.loss_module, self.learner.qnet))
        for key, value in state.get("stage1", {}).items():
            setattr(self.offline_progress, key, value)
        p = self.offline_progress
        p.stop_reason = f"from {file} ({p.stop_reason or 'stage 1'})"
        self._finish_offline()
        self.save_checkpoint()

    def _finish_offline(self) -> None:
        """The offline stage is over: save its weights (:func:`save_offline`); the next stage
        starts from them (online and target networks; a fresh Adam where it declares one)."""
        assert self.offline_checks is not None
        self.offline_checks.finish(self.learner.loss_module)
        path = save_offline(self.out_dir / "checkpoints", self.learner.loss_module, self.learner.qnet,
                            dataclasses.asdict(self.offline_progress))
        self.weights_dir = path.parent  # the next stage's teacher, where it has one
        self.learner.sync_target()
        done, following = self.counters.stage, self.spec.next_stage(self.counters.stage)
        assert following is not None, "an offline stage is followed by the stage it trains for"
        self._set_stage(following.name, following.fresh_optimizer)
        self.rounds.sync()
        log.info("offline stage %s done (%s); %s starts from %s", done,
                 self.offline_progress.stop_reason, following.name, path)

    # ------------------------------------------------------------------ bookkeeping
    def _reprioritize(self, batches: list[TensorDictBase]) -> None:
        """With ``buffer.priority``: the TD errors of the updated batches become their rows'
        priorities (:mod:`memrl.data.priority_sampler`), before the next round samples."""
        sampler = priority_sampler(self.stage.buffer)
        if sampler is not None:
            for batch in batches:
                reprioritize(sampler, batch)

    def _book(self, batches: list[TensorDictBase], losses: list[torch.Tensor]) -> None:
        """Counters, accumulators and the periodic updates.csv rows of finished updates. Their
        losses and demo counts stay on the device until ``agent.loss_readback`` of them wait
        (or a row, a check or a checkpoint needs them): one host read for all."""
        for batch, loss in zip(batches, losses, strict=True):
            self.counters.updates += 1
            self._pending.append((loss, batch["is_demo"].sum()))
            self._last_batch = batch
            if len(self._pending) >= self._readback_every:
                self._read_back()
            if self.counters.updates % int(self.cfg.log_every) == 0:
                self._log_updates()

    def _read_back(self) -> None:
        """The pending losses and demo counts, read to the host at once, into the accumulators."""
        if not self._pending:
            return
        losses = torch.stack([loss.float() for loss, _ in self._pending]).tolist()
        demos = torch.stack([demo for _, demo in self._pending]).tolist()
        self._pending = []
        self._acc["loss"].extend(losses)
        self._acc["demo"].extend(float(d) for d in demos)
        self._losses.extend(losses)

    def _log_updates(self) -> None:
        """One row of updates.csv over the updates since the last row."""
        self._read_back()
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
            "epsilon": self._epsilon(),
        }, offline=self.stage.offline)
        c.update_rows += 1
        self._acc = {"loss": [], "demo": []}

    def _epsilon(self) -> float:
        return float(self.stage.explore.eps) if self.stage.explore is not None else 0.0

    @property
    def _ckpt_every(self) -> int:
        return int(self.cfg.checkpoint_every)

    def _start_clock(self) -> None:
        self._t_start = time.perf_counter()
        self._frames0, self._updates0 = self.counters.frames, self.counters.updates
        self.rounds.update_seconds = 0.0

    def _trained_s(self, elapsed: float) -> float | None:
        """Training seconds of the run over all its calls, this one at ``elapsed`` seconds."""
        return None if self._wall_before is None else self._wall_before + elapsed

    def _progress_bar(self) -> tqdm:
        cfg, c = self.cfg, self.counters
        by_episodes = cfg.total_episodes is not None
        return progress_bar(cfg.progress, total=int(cfg.total_episodes if by_episodes else cfg.total_frames),
                            initial=c.episodes if by_episodes else c.frames, desc=f"train {self.mode}",
                            unit="episodes" if by_episodes else "frames")

    # ------------------------------------------------------------------ checkpoints
    def save_checkpoint(self) -> None:
        self._read_back()  # the accumulators it saves hold every finished update
        online = not self.stage.offline
        state = {
            "config": ckpt.comparable(self.cfg),
            "counters": dataclasses.asdict(self.counters),
            "stage1": dataclasses.asdict(self.offline_progress),
            "learner": self.learner.state_dict(),
            "explore": self.stage.explore.state_dict() if online else None,  # type: ignore[union-attr]
            "collector": self.collector.state_dict() if online else None,
            "rounds": self.rounds.state_dict(),
            "acc": self._acc,
            "recent": list(self._recent),
            "rng": ckpt.rng_state(),
            "stage1_best": self.offline_checks.best if self.offline_checks is not None else None,
            "teacher": self.teacher.state_dict() if self.teacher is not None else None,
            "wall_s": self._trained_s(time.perf_counter() - self._t_start),
        }
        agent_part = getattr(self.stage.buffer, "online_buffer", self.stage.buffer)  # not the demos
        agent_data = online and len(agent_part) > 0
        ckpt.save(self.out_dir / "checkpoints" / "last", state,
                  self.stage.buffer if agent_data else None)
        self._checkpointed_at = self.counters.episodes
        self.records.flush()  # the logger gets its points once a checkpoint covers them

    def resume(self, run_dir: Path) -> None:
        """Continue from the last complete checkpoint of ``run_dir`` (same config required)."""
        where = ckpt.find(run_dir)
        state = ckpt.load_state(where, self.cfg)
        counters = dict(state["counters"])
        offline = self.spec.stage(counters["stage"]).offline
        counters.setdefault("rounds", 0 if offline  # older format
                            else self.schedule.rounds_due(counters["frames"]))
        self.counters = Counters(**counters)
        self.offline_progress = Stage1Progress(**state["stage1"])
        self.learner.load_state_dict(state["learner"])
        self.weights_dir = Path(run_dir) / "checkpoints"
        self._set_stage(self.counters.stage)
        if self.offline_checks is not None:
            self.offline_checks.best = state.get("stage1_best")
        if self.teacher is not None and state.get("teacher") is not None:
            self.teacher.load_state_dict(state["teacher"])
            self._teach()
        if self.stage.explore is not None:
            self.stage.explore.load_state_dict(state["explore"])
        if (where / "buffer").exists():
            try:
                self.stage.buffer.loads(where / "buffer")
            except (OSError, ValueError, RuntimeError, KeyError) as err:  # no manifest to check
                raise ckpt.CheckpointError(f"{where / 'buffer'}: unreadable replay buffer "
                                           f"({type(err).__name__}: {err})") from err
        self.self_play.restore(self.counters.episodes)  # before the engine: its pool size
        if state.get("collector") is not None:  # None: made in stage 1, the collector not started yet
            self.collector.load_state_dict(state["collector"])
        elif not self.stage.offline:  # older format: single-env runs saved between episodes
            self.collector.load_state_dict({"started": self.counters.episodes,
                                            "pending": torch.ones(self.num_envs, dtype=torch.bool)})
        self._acc = state["acc"]
        self._recent = deque(state["recent"], maxlen=20)
        ckpt.set_rng_state(state["rng"])
        self.records.rewind(self.counters.episodes, self.counters.update_rows)
        self.periodic.rewind(self.counters.episodes, self.counters.frames)
        self.rounds.load_state_dict(state.get("rounds"))
        self._checkpointed_at = self.counters.episodes
        self.resumed_from = self.counters.episodes
        self._wall_before = state.get("wall_s")  # absent from older checkpoints: unknown
        log.info("resumed %s at stage %s: %d episodes, %d frames, %d updates", where,
                 self.counters.stage, self.counters.episodes, self.counters.frames,
                 self.counters.updates)

    # ------------------------------------------------------------------ the end
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
            stage1=dataclasses.asdict(self.offline_progress), wall_s=wall,
            updates_per_s=(c.updates - self._updates0) / max(wall, 1e-9),
            frames_per_s=(c.frames - self._frames0) / max(wall, 1e-9),
            learner_busy=self.rounds.update_seconds / max(wall, 1e-9),
            resumed_from_episode=self.resumed_from, num_envs=self.num_envs,
            device=str(self.device),
            train_wall_s=self._trained_s(wall))
        env_cfg = OmegaConf.to_container(self.cfg.env, resolve=True)
        save_qnet(self.out_dir / "checkpoints" / "final.pt", self.learner.qnet,
                  env_cfg, {"summary": dataclasses.asdict(summary)})  # type: ignore[arg-type]
        (self.out_dir / "summary.json").write_text(json.dumps(dataclasses.asdict(summary), indent=2))
        return summary
