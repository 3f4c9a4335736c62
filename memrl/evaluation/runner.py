"""Evaluation episodes, fast: one entry point (:func:`run_jobs`), two ways to step them.

* Actors that act from pixels alone (``Actor.tensor_policy``, e.g. the greedy Q-network) run
  on the batched engine (:mod:`memrl.evaluation.engine_runner`): every episode of the jobs
  at once, one forward pass per step, on any device.
* The others (the scripted driver reads the world state, a human needs the window, a step
  hook renders the scene) run gym envs in lockstep batches, in worker processes.

Both give the same :class:`EpisodeRecord` s (``tests/test_engine_runner.py``). Observations are
exactly those of the TorchRL pipeline (``make_env``): the env's grayscale BEV frame,
``frame_stack`` of them ``env.frame_stride`` steps apart stacked oldest first, the first frame
standing in for steps before a reset (``CatFrames``' padding); ``tests/test_evaluate.py``
checks the equality step by step. The pipeline itself is not used here because its per-step
overhead costs more than the env step.
"""

from __future__ import annotations

import logging
import math
import multiprocessing as mp
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import AbstractContextManager
from dataclasses import dataclass

import numpy as np
import torch

from memrl.envs.crash import kind_name
from memrl.envs.lane_change import LaneChangeEnv
from memrl.evaluation.crash_sight import EpisodeTrace
from memrl.evaluation.engine_runner import engine_can_run, resolve_device, run_jobs_on_engine
from memrl.evaluation.jobs import Actor, Job, JobResult, StepHook, torch_threads
from memrl.evaluation.protocol import INITIAL_LANES, EpisodeRecord, closing_or_none
from memrl.modules.policy import FrameStack, StopRecording
from memrl.progress import progress_bar
from memrl.stop import Interrupted, interrupted_by
from memrl.workers import stopped_with_parent, worker_start

__all__ = ["Actor", "FrameStack", "Job", "JobResult", "StepHook", "run_job", "run_jobs", "split",
           "torch_threads"]

log = logging.getLogger(__name__)


@dataclass
class _Slot:
    index: int
    seed: int
    stack: FrameStack
    start_lane: int
    vehicles: int
    ret: float = 0.0
    kept: dict[str, list] | None = None
    """With ``record``: per step the outputs acted on (``q``, ``risk``), the action, the reward."""

    def keep(self, action: int, values: dict[str, np.ndarray]) -> None:
        """Keep a step's action and the outputs it was chosen from (``record``)."""
        assert self.kept is not None
        self.kept["action"].append(action)
        for key, value in values.items():
            self.kept[key].append(value)

    def traces(self, record: EpisodeRecord) -> list[EpisodeTrace]:
        """The finished episode's recorded steps (none without ``record``)."""
        if self.kept is None:
            return []
        k, f32 = self.kept, np.float32
        risk = np.array(k["risk"], dtype=f32) if k["risk"] else None
        return [EpisodeTrace(record.initial_lane, self.index, np.array(k["q"], dtype=f32),
                             np.array(k["action"], dtype=np.int64), np.array(k["reward"], dtype=f32),
                             record.collided, risk)]


def one_thread() -> AbstractContextManager[None]:
    """torch on one thread for the block: one process per core is the parallelism here, and
    torch's OpenMP threads slow down by 10x and more when the cores are busy (spin-waiting)."""
    return torch_threads(1)


def run_job(actor: Actor, job: Job, batch: int = 8, frame_stack: int = 4,
            hook: StepHook | None = None, record: bool = False) -> JobResult:
    """Run the job's episodes, up to ``batch`` at a time; a finished slot takes the next one.
    ``record``: keep each episode's Q-values, actions and rewards (``gives_values`` actors)."""
    with one_thread():
        return _run_job(actor, job, batch, frame_stack, hook, record and actor.gives_values)


def _run_job(actor: Actor, job: Job, batch: int, frame_stack: int, hook: StepHook | None,
             record: bool = False) -> JobResult:
    batch = max(1, min(batch if actor.batchable else 1, len(job.episodes)))
    render = "rgb_array" if actor.needs_render or hook is not None else None
    envs = [LaneChangeEnv(config=job.env, render_mode=render) for _ in range(batch)]
    queue = list(job.episodes)
    slots: list[_Slot | None] = [None] * batch
    result = JobResult()
    try:
        while True:
            for s, env in enumerate(envs):
                if slots[s] is None and queue:
                    slots[s] = _start(actor, s, env, *queue.pop(0), frame_stack, hook, record)
            running = [s for s in range(batch) if slots[s] is not None]
            if not running:
                break
            pixels = np.stack([slots[s].stack.frames for s in running])  # type: ignore[union-attr,misc]
            actions = _act(actor, running, envs, slots, pixels, record)  # type: ignore[arg-type]
            for s, action in zip(running, actions, strict=True):
                slot = slots[s]
                rec = _step(envs[s], slot, int(action), job, hook)  # type: ignore[arg-type]
                if rec is not None:
                    result.records.append(rec)
                    result.traces += slot.traces(rec)  # type: ignore[union-attr]
                    slots[s] = None
    except StopRecording:
        log.info("evaluation stopped after %d finished episodes", len(result.records))
        result.stopped_early = True
    except (KeyboardInterrupt, Interrupted) as err:  # Ctrl-C, SIGTERM: keep what finished
        log.info("evaluation interrupted after %d finished episodes", len(result.records))
        result.stopped_early, result.interrupted = True, interrupted_by(err)
    finally:
        for env in envs:
            env.close()
    return result


def _act(actor: Actor, running: list[int], envs: list[LaneChangeEnv], slots: list[_Slot],
         pixels: np.ndarray, record: bool) -> np.ndarray:
    """The running slots' actions; with ``record``, from the actor's values, kept per slot."""
    if not record:
        return actor.act(running, [envs[s] for s in running], pixels)
    acts, outs = actor.act_values(torch.from_numpy(pixels))
    actions = acts.cpu().numpy()
    values = {k: v.cpu().numpy() for k, v in outs.items() if k in ("q", "risk")}
    for j, s in enumerate(running):
        slots[s].keep(int(actions[j]), {k: v[j] for k, v in values.items()})
    return actions


def _start(actor: Actor, slot: int, env: LaneChangeEnv, index: int, seed: int, frame_stack: int,
           hook: StepHook | None, record: bool = False) -> _Slot:
    obs, _ = env.reset(seed=seed)
    stack = FrameStack(frame_stack, env.cfg.frame_stride)
    stack.reset(obs)
    actor.begin(slot, env, seed)
    if hook is not None:
        hook(env, stack.frames, None, None)  # type: ignore[arg-type]
    kept: dict[str, list] | None = {"q": [], "risk": [], "action": [], "reward": []} if record else None
    return _Slot(index, seed, stack, env.current_lane(), len(env.others), kept=kept)


def _step(env: LaneChangeEnv, slot: _Slot, action: int, job: Job, hook: StepHook | None
          ) -> EpisodeRecord | None:
    obs, reward, terminated, truncated, info = env.step(action)
    slot.stack.push(obs)
    slot.ret += float(reward)
    if slot.kept is not None:
        slot.kept["reward"].append(float(reward))
    record = None
    if terminated or truncated:
        record = EpisodeRecord(
            initial_lane=job.initial_lane, episode=slot.index, seed=slot.seed, steps=env.steps,
            episode_return=slot.ret, collided=bool(info["collided"]),
            reached_target=bool(info["reached_target"]), duration=env.cfg.duration,
            target_lane=int(env.target_lane), start_lane=slot.start_lane, vehicles=slot.vehicles,
            crash_kind=kind_name(int(info["crash_kind"])),
            closing_speed=closing_or_none(int(info["crash_kind"]), float(info["closing_speed"])))
    if hook is not None:
        hook(env, slot.stack.frames, action, record)  # type: ignore[arg-type]
    return record


def split(jobs: Sequence[Job], parts: int) -> list[Job]:
    """Cut jobs into about ``parts`` pieces of similar size (for worker processes)."""
    total = sum(len(j.episodes) for j in jobs)
    size = max(1, math.ceil(total / max(1, parts)))
    return [Job(j.env, j.initial_lane, j.episodes[i:i + size])
            for j in jobs for i in range(0, len(j.episodes), size)]


def run_jobs(actor: Actor, jobs: Sequence[Job], *, workers: int = 1, batch: int = 8,
             progress: bool = False, desc: str = "evaluate", device: torch.device | str = "cpu",
             engine_batch: int | None = None, engine: bool | None = None,
             record: bool = False) -> JobResult:
    """Run all jobs; records come back sorted by (initial lane, episode index), whatever the split.

    Args:
        actor: the policy.
        jobs: env configs, initial lanes and (episode index, reset seed) pairs.
        workers: gym path: processes (when the actor allows it); engine path: torch threads
            on CPU.
        batch: gym path: envs stepped in lockstep per process.
        progress: show a progress bar.
        desc: its label.
        device: engine path: where the envs and the actor run (``auto``, ``cpu``, ``cuda[:K]``).
        engine_batch: engine path: envs per job at once (None: all of the job's episodes).
        engine: force (True) or forbid (False) the engine path; None: the engine for
            ``tensor_policy`` actors on jobs it can run (:func:`engine_can_run`).
        record: keep each episode's Q-values, actions and rewards (``JobResult.traces``) when
            the actor gives them (``gives_values``): what the crash-sight section reads.
    """
    total = sum(len(j.episodes) for j in jobs)
    bar = progress_bar(progress, total=total, desc=desc, unit="ep")
    out = JobResult()
    use_engine = actor.tensor_policy and all(engine_can_run(j) for j in jobs) if engine is None else engine
    if use_engine:
        dev = resolve_device(device)
        threads = max(1, workers) if dev.type == "cpu" else torch.get_num_threads()
        out = run_jobs_on_engine(actor, jobs, batch=engine_batch, device=dev, threads=threads,
                                 on_done=bar.update, record=record)
    elif workers > 1 and actor.parallel:
        # spawn, not fork: a forked child may hang in torch's thread pool
        pieces = split(jobs, 4 * workers)
        with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"),
                                 initializer=worker_start) as pool, stopped_with_parent(pool):
            futures = [pool.submit(run_job, actor, piece, batch, record=record) for piece in pieces]
            for future in as_completed(futures):
                res = future.result()
                out.records += res.records
                out.traces += res.traces
                bar.update(len(res.records))
    else:
        for job in jobs:
            res = run_job(actor, job, batch, record=record)
            out.records += res.records
            out.traces += res.traces
            bar.update(len(res.records))
            if res.stopped_early:
                out.stopped_early, out.interrupted = True, res.interrupted
                break
    bar.close()
    order = {lane: i for i, lane in enumerate(INITIAL_LANES)}
    out.records.sort(key=lambda r: (order.get(r.initial_lane, 99), r.episode))
    out.traces.sort(key=lambda t: (order.get(t.initial_lane, 99), t.episode))
    return out
