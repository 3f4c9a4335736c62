"""Evaluation episodes on the batched engine: every episode of the jobs at once, one forward.

For actors that act from pixels alone (``Actor.tensor_policy``: the greedy Q-network). Each
job (one env config: the protocol's rules for one initial lane) gets its own
:class:`~memrl.envs.batched.BatchedLaneChange` with up to ``batch`` envs; every step, the
stacked pixels of the running episodes of *all* jobs go through the actor in one call, each
engine steps, and an env whose episode ended starts the job's next queued episode (reset with
its seed: the gym env's scene of that seed). The records are those of the gym-env path of
:func:`~memrl.evaluation.runner.run_jobs`, episode by episode (``tests/test_engine_runner.py``):
the engine is the reference env step for step (``tests/test_batched.py``).

:func:`run_actors_on_engine` drives the same jobs for K actors (K checkpoints) on one engine per
job: every env slot drives one actor's episode, each step each actor acts on its own envs' stacks,
and each actor's records are those it gets on its own (``tests/test_engine_runner.py``).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Sequence

import torch

from memrl.envs.batched import BatchedLaneChange, StepOut, resolve_device
from memrl.envs.config import EnvConfigError, env_config_dict, validate_env_config
from memrl.envs.crash import kind_name
from memrl.envs.vehicles import IDLE
from memrl.evaluation.crash_sight import EpisodeTrace
from memrl.evaluation.jobs import Actor, Job, JobResult, torch_threads
from memrl.evaluation.protocol import EpisodeRecord, closing_or_none

__all__ = ["engine_can_run", "resolve_device", "run_actors_on_engine", "run_jobs_on_engine", "torch_threads"]


def engine_can_run(job: Job) -> bool:
    """Whether the engine gives this job's gym observations: grayscale frames, one per env
    step (``frame_stack: 1``; the runners stack them), as the evaluation's env configs have.
    A config the engine cannot read (highway-env's own keys, a bad value) is left to the gym
    env and its message."""
    try:
        cfg = validate_env_config({**env_config_dict(), **dict(job.env)})
    except EnvConfigError:
        return False
    return bool(cfg.bev.grayscale) and cfg.frame_stack == 1


class _Lane:
    """One job on its own engine of up to ``batch`` envs per actor: which actor's episode each
    env drives."""

    def __init__(self, job: Job, batch: int | None, device: torch.device, frame_stack: int,
                 owners: int = 1) -> None:
        n = owners * min(batch or len(job.episodes), len(job.episodes))
        self.job = job
        self.queue = deque((k, i, s) for i, s in job.episodes for k in range(owners))
        """(actor, episode index, reset seed) still to drive, the actors taking turns (every
        actor drives from the first step: the first step's outputs hold every key)."""
        self.engine = BatchedLaneChange(job.env, n, device, frame_stack)
        self.index, self.seed = [-1] * n, [0] * n
        """Episode index (-1: idle, the queue ran out) and reset seed per env."""
        self.owner = torch.zeros(n, dtype=torch.long, device=device)
        """The actor whose episode each env drives."""
        self.start_lane, self.target_lane, self.vehicles = [-1] * n, [-1] * n, [-1] * n
        self.ret = torch.zeros(n, dtype=torch.float64, device=device)
        """Return so far per env, summed step by step in float64 like the gym path."""
        self.steps = torch.zeros(n, dtype=torch.long, device=device)
        self.active = torch.zeros(n, dtype=torch.bool, device=device)
        """Envs driving an episode that counts."""
        self.trace: dict[str, torch.Tensor] = {}
        """With ``record``: per env and step of its episode, the outputs acted on (``q``
        ``[n, duration, A]``, ``risk``), the action and the reward; made at the first
        :meth:`keep_step`."""
        self.fill(range(n))

    def keep_step(self, actions: torch.Tensor, outputs: dict[str, torch.Tensor],
                  reward: torch.Tensor) -> None:
        """Write this step's row of :attr:`trace` for the active envs (before ``steps`` counts
        it): ``actions`` and ``outputs`` hold one row per active env, in env order."""
        idx = torch.nonzero(self.active).flatten()
        if not self.trace:
            n, length, dev = self.engine.num_envs, int(self.engine.cfg.duration), self.engine.device
            self.trace = {key: torch.zeros((n, length, *v.shape[1:]), dtype=torch.float32, device=dev)
                          for key, v in outputs.items() if key in ("q", "risk")}
            self.trace["action"] = torch.zeros((n, length), dtype=torch.long, device=dev)
            self.trace["reward"] = torch.zeros((n, length), dtype=torch.float32, device=dev)
        t = self.steps[idx]
        for key in ("q", "risk"):
            if key in self.trace:
                self.trace[key][idx, t] = outputs[key].to(self.trace[key])
        self.trace["action"][idx, t] = actions
        self.trace["reward"][idx, t] = reward[idx].float()

    def traces(self, ids: list[int], collided: list[bool],
               gives_risk: Sequence[bool] = (True,)) -> list[EpisodeTrace]:
        """The recorded steps of the episodes that just ended in envs ``ids`` (a risk row for
        the actors ``gives_risk`` marks)."""
        if not self.trace:
            return []
        rows = {key: v[ids].cpu().numpy() for key, v in self.trace.items()}
        steps, owner = self.steps[ids].tolist(), self.owner[ids].tolist()
        return [EpisodeTrace(self.job.initial_lane, self.index[i], rows["q"][k, :n],
                             rows["action"][k, :n], rows["reward"][k, :n], bool(c),
                             rows["risk"][k, :n] if "risk" in rows and gives_risk[o] else None)
                for k, (i, n, c, o) in enumerate(zip(ids, steps, collided, owner, strict=True))]

    def fill(self, ids: Sequence[int]) -> None:
        """Start the next queued episodes in envs ``ids``; the ones left over go idle."""
        start, owners = [], []
        for i in ids:
            if self.queue:
                k, self.index[i], self.seed[i] = self.queue.popleft()
                start.append(i)
                owners.append(k)
            else:
                self.index[i] = -1
                self.active[i] = False
        if not start:
            return
        self.engine.reset(start, [self.seed[i] for i in start])
        info = self.engine.info()
        lanes, targets = info["lane"].tolist(), info["target_lane"].tolist()
        cars = (self.engine.present.sum(-1) - 1).tolist()  # other cars in each scene
        for i in start:
            self.start_lane[i], self.target_lane[i], self.vehicles[i] = lanes[i], targets[i], cars[i]
        idx = torch.as_tensor(start, device=self.engine.device)
        self.owner[idx] = torch.as_tensor(owners, device=self.engine.device)
        self.ret[idx] = 0.0
        self.steps[idx] = 0
        self.active[idx] = True

    def finish(self, ids: list[int], out: StepOut) -> list[EpisodeRecord]:
        """The records of the episodes that just ended in envs ``ids`` (``out``: the step's)."""
        rets, steps = self.ret.tolist(), self.steps.tolist()
        collided, reached = out.collided[ids].tolist(), out.reached_target[ids].tolist()
        assert out.crash_kind is not None and out.closing_speed is not None
        kinds, closing = out.crash_kind[ids].tolist(), out.closing_speed[ids].tolist()
        return [EpisodeRecord(
            initial_lane=self.job.initial_lane, episode=self.index[i], seed=self.seed[i], steps=steps[i],
            episode_return=rets[i], collided=c, reached_target=r, duration=self.engine.cfg.duration,
            target_lane=self.target_lane[i], start_lane=self.start_lane[i], vehicles=self.vehicles[i],
            crash_kind=kind_name(k), closing_speed=closing_or_none(k, v))
            for i, c, r, k, v in zip(ids, collided, reached, kinds, closing, strict=True)]


def run_jobs_on_engine(actor: Actor, jobs: Sequence[Job], *, batch: int | None = None,
                       device: torch.device | str = "cpu", frame_stack: int = 4, threads: int = 1,
                       on_done: Callable[[int], object] | None = None, record: bool = False) -> JobResult:
    """Run the jobs' episodes on batched engines; records in the order they finish.

    Args:
        actor: a ``tensor_policy`` actor (moved to ``device``).
        jobs: env configs, initial lanes and (episode index, reset seed) pairs.
        batch: envs per job at once (None: all of the job's episodes).
        device: where the engines and the actor run.
        frame_stack: frames per observation.
        threads: torch CPU threads for the run.
        on_done: called with the number of episodes finished at each step that finishes some.
        record: keep each episode's Q-values, actions and rewards (``JobResult.traces``;
            ``gives_values`` actors only).
    """
    [out] = run_actors_on_engine([actor], jobs, batch=batch, device=device, frame_stack=frame_stack,
                                 threads=threads, on_done=on_done, record=record)
    return out


def _act(actor: Actor, pixels: torch.Tensor, steps: torch.Tensor | None, record: bool,
         dev: torch.device) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    if record:
        actions, outputs = actor.act_values(pixels)
        return actions.to(dev), outputs
    if actor.needs_steps:
        assert steps is not None
        return actor.act_steps(pixels, steps).to(dev), {}
    return actor.act_pixels(pixels).to(dev), {}


def _act_each(actors: Sequence[Actor], pixels: torch.Tensor, steps: torch.Tensor | None, owner: torch.Tensor,
              records: Sequence[bool], gives_risk: list[bool],
              dev: torch.device) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Each actor on its own envs' stacks (``owner``: the actor of each row); marks in
    ``gives_risk`` the actors whose outputs hold a risk."""
    actions = torch.full((len(pixels),), IDLE, dtype=torch.long, device=dev)
    outputs: dict[str, torch.Tensor] = {}
    for k, actor in enumerate(actors):
        sel = torch.nonzero(owner == k).flatten()
        if len(sel) == 0:
            continue
        act, out = _act(actor, pixels[sel], None if steps is None else steps[sel], records[k], dev)
        actions[sel] = act
        gives_risk[k] = gives_risk[k] or "risk" in out
        for key, v in out.items():
            if key not in outputs:
                outputs[key] = torch.zeros((len(pixels), *v.shape[1:]), dtype=v.dtype, device=v.device)
            outputs[key][sel.to(v.device)] = v
    return actions, outputs


def _collect(lane: _Lane, ids: list[int], out: StepOut, results: Sequence[JobResult],
             records: Sequence[bool], gives_risk: Sequence[bool]) -> int:
    """The episodes that just ended in ``lane``'s envs ``ids`` into their actors' results;
    returns how many."""
    owners = lane.owner[ids].tolist()
    finished = lane.finish(ids, out)
    traces = lane.traces(ids, [r.collided for r in finished], gives_risk) if any(records) else []
    by_id = dict(zip(ids, traces, strict=True)) if traces else {}
    for i, k, rec in zip(ids, owners, finished, strict=True):
        results[k].records.append(rec)
        if records[k] and i in by_id:
            results[k].traces.append(by_id[i])
    return len(finished)


def run_actors_on_engine(actors: Sequence[Actor], jobs: Sequence[Job], *, batch: int | None = None,
                         device: torch.device | str = "cpu", frame_stack: int = 4, threads: int = 1,
                         on_done: Callable[[int], object] | None = None,
                         record: bool = False) -> list[JobResult]:
    """Run the jobs' episodes for each of ``actors`` (e.g. K checkpoints) on one batched engine
    per job; each actor's records (and traces) in the order they finish, what
    :func:`run_jobs_on_engine` gives it alone. Arguments as there; ``batch`` counts envs per
    job and actor, ``record`` applies to the ``gives_values`` actors."""
    for actor in actors:
        if not actor.tensor_policy:
            raise TypeError(f"{type(actor).__name__} acts through the env; the engine runs "
                            "tensor_policy actors")
    dev = resolve_device(device)
    for actor in actors:
        actor.to(dev)
    records = [record and a.gives_values for a in actors]
    gives_risk = [False] * len(actors)
    results = [JobResult() for _ in actors]
    with torch_threads(threads):
        lanes = [_Lane(job, batch, dev, frame_stack, len(actors)) for job in jobs if job.episodes]
        while live := [lane for lane in lanes if bool(lane.active.any())]:
            pixels = [lane.engine.observation()[lane.active] for lane in live]
            batch_px = torch.cat(pixels) if len(pixels) > 1 else pixels[0]
            steps = torch.cat([lane.steps[lane.active] for lane in live]) \
                if any(a.needs_steps for a in actors) else None
            if len(actors) == 1:
                actions, outputs = _act(actors[0], batch_px, steps, records[0], dev)
                gives_risk[0] = "risk" in outputs
            else:
                owner = torch.cat([lane.owner[lane.active] for lane in live])
                actions, outputs = _act_each(actors, batch_px, steps, owner, records, gives_risk, dev)
            offset = 0
            for lane, px in zip(live, pixels, strict=True):
                part = slice(offset, offset + len(px))
                chosen = torch.full((lane.engine.num_envs,), IDLE, dtype=torch.long, device=dev)
                chosen[lane.active] = actions[part]
                offset += len(px)
                out = lane.engine.step(chosen, active=lane.active)
                if outputs:
                    lane.keep_step(actions[part], {k: v[part] for k, v in outputs.items()}, out.reward)
                lane.ret += torch.where(lane.active, out.reward, 0.0)
                lane.steps += lane.active.long()
                done = (out.terminated | out.truncated) & lane.active
                ids = torch.nonzero(done).flatten().tolist()
                if ids:
                    count = _collect(lane, ids, out, results, records, gives_risk)
                    lane.fill(ids)
                    if on_done is not None:
                        on_done(count)
    return results
