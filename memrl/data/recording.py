"""Record episodes of any :class:`DrivingPolicy` through the TorchRL env into demo datasets.

Episodes run through ``make_env`` + :class:`PolicyModule`, so the stored pixels are exactly
what training sees. Episode ``i`` is reset with seed ``seed + i``.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch
from filelock import FileLock
from tensordict import TensorDict

from memrl.data.demos import (
    DemoDatasetError,
    EnvCfg,
    example_demos_path,
    load_demos,
    recording_env,
    save_demos,
)
from memrl.data.recipe import recipe_error, recipe_values
from memrl.data.sittings import Plan, clean_stale, write_progress
from memrl.data.transitions import to_transitions
from memrl.envs.config import LaneChangeConfig
from memrl.envs.lane_change import LaneChangeEnv
from memrl.envs.torchrl_env import env_kwargs, make_env, unwrap
from memrl.modules.policy import DrivingPolicy, FrameStack, PerturbedPolicy, PolicyModule, StopRecording
from memrl.progress import progress_bar
from memrl.stop import Interrupted, SignalGuard, interrupted_by

log = logging.getLogger(__name__)


@dataclass
class EpisodeStats:
    """Outcome of one recorded episode."""

    seed: int
    steps: int
    """Action steps taken."""
    episode_return: float
    """Sum of rewards."""
    collided: bool
    reached_target: bool
    """All four corners of the car inside the target lane at some step."""
    perturbed: int = 0
    """Steps whose executed action was the recording noise's, not the driver's (not stored)."""

    @property
    def stable(self) -> bool:
        """No collision and the target lane reached: what prior knowledge should show."""
        return not self.collided and self.reached_target


def summarize(episodes: list[EpisodeStats]) -> dict[str, Any]:
    """Counts and rates: survival (no collision), goal (target lane reached), mean return."""
    n = len(episodes)
    survival = sum(not e.collided for e in episodes)
    goal = sum(e.reached_target for e in episodes)
    return {
        "episodes": n,
        "transitions": sum(e.steps for e in episodes),
        "survival": survival,
        "goal": goal,
        "survival_rate": survival / n if n else 0.0,
        "goal_rate": goal / n if n else 0.0,
        "mean_return": sum(e.episode_return for e in episodes) / n if n else 0.0,
    }


@dataclass
class Recording:
    """Recorded episodes and the transitions of the kept ones (one TensorDict per episode)."""

    episodes: list[EpisodeStats] = field(default_factory=list)
    kept: list[int] = field(default_factory=list)
    """Indices into ``episodes`` of the kept episodes."""
    transitions: list[TensorDict] = field(default_factory=list)
    stopped_early: bool = False
    interrupted: Interrupted | None = None
    """The signal that stopped it (SIGINT, SIGTERM); None: none did."""
    next_episode: int = 0
    """Index of the first episode not finished (where a later sitting goes on)."""

    def stats(self) -> dict[str, Any]:
        """Counts over the recorded and the kept episodes. ``kept.transitions`` counts the
        transitions stored (``tail_steps`` and noise steps cut), ``kept.steps`` the episodes' steps."""
        kept = summarize([self.episodes[i] for i in self.kept])
        kept["steps"] = kept["transitions"]
        kept["transitions"] = sum(int(t.shape[0]) for t in self.transitions)
        return {"recorded": summarize(self.episodes), "kept": kept}


def reached_index(rollout: TensorDict) -> int | None:
    """Index of the first step of a rollout after which the target lane was reached (None: never)."""
    hits = rollout["next", "reached_target"].reshape(-1).nonzero()
    return int(hits[0]) if len(hits) else None


def record_episodes(env_cfg: EnvCfg, policy: DrivingPolicy, *, episodes: int, seed: int = 0,
                    keep_stable: bool = True, tail_steps: int | None = None,
                    action_noise: float = 0.0, frame_stack: int = 4, render: bool = False,
                    progress: bool = False, start: int = 0, kept_before: int = 0) -> Recording:
    """Run episodes ``start .. episodes - 1`` of ``policy`` and keep the transitions of the chosen ones.

    Args:
        env_cfg: lane-change env config.
        policy: the driver; it may raise :class:`StopRecording` to end early.
        episodes: episodes to run.
        seed: episode ``i`` is reset with ``seed + i``.
        keep_stable: keep only episodes without collision that reached the target lane;
            False keeps all.
        tail_steps: keep only the first ``tail_steps`` transitions after the step that reached
            the target lane (None: the whole episode). The episode is still run to its end and
            judged stable on the whole of it; the stored part ends without a terminal flag, so
            its last transition bootstraps. This puts the prior knowledge on the manoeuvre
            (waiting for a gap, changing, settling) instead of on long lane keeping.
        action_noise: probability per step of executing a uniform random action instead of
            the policy's (:class:`PerturbedPolicy`, seeded with ``seed``); those steps are not
            stored, so the kept transitions show the policy recovering from the noise's
            off-path states. 0: the policy alone.
        frame_stack: stacked frames per observation.
        render: build the env with ``render_mode='rgb_array'`` (for a policy that shows the
            scene, like the keyboard recorder).
        progress: show a progress bar.
        start: first episode index (a later sitting of a stopped recording).
        kept_before: episodes kept in earlier sittings (for the driver's window).

    Esc (:class:`StopRecording`), Ctrl-C and SIGTERM (:class:`memrl.stop.Interrupted`) end it
    early: the episode under way is dropped, the finished ones are returned.
    """
    env = make_env(env_config_values(env_cfg), frame_stack=frame_stack,
                   render_mode="rgb_array" if render else None)
    noisy = PerturbedPolicy(policy, action_noise, seed=seed) if action_noise > 0 else None
    module = PolicyModule(noisy or policy, unwrap(env))
    duration = unwrap(env).cfg.duration
    rec = Recording(next_episode=start)
    try:
        for i in progress_bar(progress, iterable=range(start, episodes), desc="record", unit="ep"):
            if hasattr(policy, "progress"):
                policy.progress = (i + 1, episodes, kept_before + len(rec.kept))
            td = env.reset(seed=seed + i)
            rollout = env.rollout(duration, module, auto_reset=False, tensordict=td,
                                  break_when_any_done=True)
            last = rollout[-1]["next"]
            perturbed = torch.tensor(noisy.perturbed if noisy else [], dtype=torch.bool)
            stats = EpisodeStats(
                seed=seed + i, steps=rollout.shape[0],
                episode_return=float(rollout["next", "reward"].sum()),
                collided=bool(last["collided"]), reached_target=bool(last["reached_target"]),
                perturbed=int(perturbed.sum()),
            )
            stored = None
            if stats.stable or not keep_stable:
                if tail_steps is not None and (reached := reached_index(rollout)) is not None:
                    rollout = rollout[:reached + 1 + tail_steps]
                if noisy is not None:  # store only the steps of the policy's own action
                    rollout = rollout[~perturbed[:rollout.shape[0]]]
                stored = to_transitions(rollout, is_demo=True)
            rec.episodes.append(stats)  # an episode counts once all of it is in hand
            if stored is not None:
                rec.kept.append(len(rec.episodes) - 1)
                rec.transitions.append(stored)
            rec.next_episode = i + 1
    except StopRecording:
        log.info("recording stopped after %d finished episodes", len(rec.episodes))
        rec.stopped_early = True
    except (KeyboardInterrupt, Interrupted) as err:
        log.info("recording interrupted after %d finished episodes", len(rec.episodes))
        rec.stopped_early, rec.interrupted = True, interrupted_by(err)
    finally:
        env.close()
        close = getattr(policy, "close", None)
        if callable(close):
            close()
    return rec


def drive_episodes(env_cfg: EnvCfg, policy: DrivingPolicy, seeds: Iterable[int],
                   frame_stack: int = 4) -> list[EpisodeStats]:
    """Run a policy on the gym env directly: same episodes as :func:`record_episodes` for the
    same seeds, without the TorchRL pipeline (about 6x faster), for measuring policies that
    read the world state. ``pixels`` are still passed as a stack of the last frames.
    """
    # Hand-written: TorchRL's rollout costs more than the whole env step here.
    env = LaneChangeEnv(config=env_config_values(env_cfg))
    stack = FrameStack(frame_stack, int(env.cfg.frame_stride))
    out = []
    try:
        for seed in seeds:
            obs, _ = env.reset(seed=seed)
            stack.reset(obs)
            policy.reset(env)
            total, done, info = 0.0, False, {}
            while not done:
                obs, reward, terminated, truncated, info = env.step(policy.act(env, stack.frames))  # type: ignore[arg-type]
                stack.push(obs)
                total += float(reward)
                done = terminated or truncated
            out.append(EpisodeStats(seed=int(seed), steps=env.steps, episode_return=total,
                                    collided=bool(info["collided"]),
                                    reached_target=bool(info["reached_target"])))
    finally:
        env.close()
    return out


def env_config_values(env_cfg: EnvCfg) -> dict[str, Any]:
    """Plain dict of a (partial) env config, for the metadata."""
    if isinstance(env_cfg, LaneChangeConfig):
        return asdict(env_cfg)
    return env_kwargs(env_cfg)


def record_to_dataset(env_cfg: EnvCfg, policy: DrivingPolicy, path: str | os.PathLike, *,
                      episodes: int, seed: int = 0, keep_stable: bool = True,
                      tail_steps: int | None = None, action_noise: float = 0.0, source: str,
                      frame_stack: int = 4, render: bool = False, progress: bool = False,
                      overwrite: bool = False, extra: Mapping[str, Any] | None = None,
                      person: str | None = None, resume: tuple[Plan, Any] | None = None,
                      guard: SignalGuard | None = None) -> tuple[Path | None, Recording]:
    """Record episodes and save the kept ones as a dataset (None when nothing was kept).

    Args:
        env_cfg, policy, episodes, seed, keep_stable, tail_steps, action_noise, frame_stack,
            render, progress: as :func:`record_episodes`.
        path: dataset folder to write.
        source: who made the transitions (``scripted``, ``human``, ...), stored in the metadata.
        overwrite: replace an existing dataset at ``path``.
        extra: more metadata entries (e.g. the policy's config).
        person: who drove (``demos.person``), stored in the metadata.
        resume: the plan and saved transitions of a stopped recording at ``path``
            (:func:`memrl.data.sittings.read_plan`): its episodes go on where they stopped and
            the dataset is saved with the old and the new ones. The other arguments must be
            the plan's.
        guard: signals wait while the dataset is being saved (it is saved whole or not at all).

    A recording stopped early is saved with its plan (``sittings`` in the metadata, or only
    ``progress.json`` when no episode was kept yet), so that ``resume`` can go on with it.
    Hidden ``.<name>.tmp-*`` folders left beside ``path`` by an interrupted save are removed.
    """
    path = Path(path)
    plan, previous = resume if resume is not None else (None, None)
    rec = record_episodes(env_cfg, policy, episodes=episodes, seed=seed, keep_stable=keep_stable,
                          tail_steps=tail_steps, action_noise=action_noise,
                          frame_stack=frame_stack, render=render, progress=progress,
                          start=plan.next_episode if plan else 0,
                          kept_before=len(plan.kept) if plan else 0)
    new_episodes = len(rec.episodes)
    if plan is not None:  # the earlier sittings first
        earlier = [EpisodeStats(**e) for e in plan.recorded]
        rec.episodes = earlier + rec.episodes
        rec.kept = list(plan.kept) + [len(earlier) + k for k in rec.kept]
        rec.transitions = ([previous] if previous is not None else []) + rec.transitions
        overwrite = True
    now = Plan(episodes=episodes, seed=seed, keep="stable" if keep_stable else "all",
               tail_steps=tail_steps, action_noise=action_noise, source=source, person=person,
               next_episode=rec.next_episode, env_config=env_config_values(env_cfg),
               recorded=[asdict(e) for e in rec.episodes], kept=list(rec.kept))
    clean_stale(path)
    if plan is not None and new_episodes == 0:
        return (path if previous is not None else None), rec  # nothing new: the folder stays
    if not rec.transitions:
        if rec.stopped_early and rec.episodes:
            write_progress(path, now)
            log.warning("no episode kept out of %d recorded; the plan is in %s", len(rec.episodes), path)
        else:
            log.warning("no episode kept out of %d recorded; nothing saved", len(rec.episodes))
        return None, rec
    kept = [rec.episodes[i] for i in rec.kept]
    metadata = {
        "source": source,
        "person": person,
        "seed": seed,
        "keep": now.keep,
        "tail_steps": tail_steps,
        "action_noise": action_noise,
        "env_config": env_config_values(env_cfg),
        "frame_stack": frame_stack,
        "counts": {"episodes": len(kept), "episodes_recorded": len(rec.episodes)},
        "stats": rec.stats(),
        "episodes": [asdict(e) for e in kept],
        "sittings": now.to_json(),
        **dict(extra or {}),
    }
    with guard.deferred() if guard is not None else contextlib.nullcontext():
        try:
            return save_demos(rec.transitions, path, metadata, overwrite=overwrite), rec
        except OSError as err:
            if err.filename is None:  # e.g. a full disk inside numpy's zip writer names no file
                raise OSError(err.errno, err.strerror or str(err), str(path)) from err
            raise


def record_recipe(env_cfg: EnvCfg, recipe: Any, path: str | os.PathLike, *,
                  overwrite: bool = False, progress: bool = False,
                  extra: Mapping[str, Any] | None = None) -> tuple[Path | None, Recording]:
    """Record the scripted driver's dataset that ``recipe`` (a :class:`DemoRecipe` or its
    values) describes into ``path``, in ``env_cfg`` with the recipe's episode keys changed."""
    from memrl.modules.scripted import ScriptedDriver

    r = recipe_values(recipe)
    if (bad := recipe_error(r)) is not None:
        raise ValueError(f"demo recipe '{bad[0]}': {bad[1]}")
    env = recording_env(env_cfg, r)
    return record_to_dataset(
        env, ScriptedDriver(**r["driver"]), path, episodes=r["episodes"], seed=r["seed"],
        keep_stable=True, tail_steps=r["tail_steps"], action_noise=float(r["action_noise"]),
        source="scripted", overwrite=overwrite, progress=progress,
        extra={"policy": {"_target_": "memrl.modules.scripted.ScriptedDriver", **r["driver"]},
               "recipe": r, **dict(extra or {})})


def ensure_example_demos(env_cfg: EnvCfg = None, data_dir: str | os.PathLike | None = None,
                         recipe: Any = None, *, overwrite: bool = False,
                         progress: bool = False) -> Path:
    """Path of the cached scripted-driver dataset of ``recipe`` (None: the default
    :class:`DemoRecipe`) for ``env_cfg``; records it if needed.

    Cached under ``data_dir`` by env-config hash and recipe hash. A cached dataset that fails
    :func:`load_demos` is recorded again. Processes that ask for the same dataset at once (a
    study's parallel jobs on an empty cache) record it once: the others wait on a file lock
    beside it, then load what the first one saved.
    """
    path = example_demos_path(env_cfg, data_dir, recipe)
    path.parent.mkdir(parents=True, exist_ok=True)
    with FileLock(path.parent / f".{path.name}.lock"):  # filelock: an OS lock, gone with its process
        if path.exists() and not overwrite:
            try:
                load_demos(path, env_cfg)
                return path
            except DemoDatasetError as e:
                log.warning("cached example dataset is unusable, recording it again: %s", e)
        r = recipe_values(recipe)
        log.info("recording the example dataset (%d scripted episodes) into %s", r["episodes"], path)
        saved, rec = record_recipe(env_cfg, r, path, overwrite=True, progress=progress,
                                   extra={"example": True})
    if saved is None:
        raise RuntimeError(f"the scripted driver kept no stable episode out of {r['episodes']}; "
                           f"recorded: {rec.stats()['recorded']}")
    return path
