"""``python -m memrl.train [+mode=A|B] [+experiment=smoke] [-m] [key=value ...]``."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import hydra
from omegaconf import DictConfig, OmegaConf

from memrl.cli import run_hydra, run_task
from memrl.configs import register_configs
from memrl.schemas import check_train, check_writable
from memrl.stop import Interrupted, deferred, interruption

if TYPE_CHECKING:  # torch and the trainer load on the first run, not for --help
    from tensordict import TensorDictBase

    from memrl.dqn.loop import Summary, Trainer

log = logging.getLogger(__name__)
T = TypeVar("T")


def prior_knowledge(cfg: DictConfig) -> TensorDictBase:
    """The demo transitions of ``mode.demos_path`` (checked against the env config), or the
    scripted driver's dataset of ``mode.example`` (recorded once, then cached) when it is null."""
    from memrl.data import demos

    path = cfg.mode.demos_path
    if path is None:
        recipe = cfg.mode.example
        if not demos.example_demos_path(cfg.env, Path(cfg.paths.data_dir), recipe).exists():
            check_writable(cfg.paths.data_dir, "paths.data_dir")  # before recording it
        from memrl.data.recording import ensure_example_demos

        path = ensure_example_demos(cfg.env, Path(cfg.paths.data_dir), recipe,
                                    progress=bool(cfg.progress))
    td = demos.load_demos(Path(path), env_cfg=cfg.env)
    log.info("prior knowledge: %s (%d transitions)", Path(path).resolve(), td.shape[0])
    return td


def remove_new_entries(folder: Path, before: set[Path] | None) -> None:
    """Remove what appeared in ``folder`` since ``before`` was listed (None: the folder is new)."""
    import shutil

    if before is None:
        shutil.rmtree(folder, ignore_errors=True)
        return
    for entry in set(folder.iterdir()) - before:
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry, ignore_errors=True)
        else:
            entry.unlink(missing_ok=True)


def budget_reached(cfg: DictConfig, summary: dict) -> bool:
    """Whether a run that ended as ``summary`` (its ``summary.json``) is within ``cfg``'s budget."""
    from memrl.dqn.schedule import Budget

    return Budget(cfg.total_frames, cfg.total_episodes).done(summary["frames"], summary["episodes"])


def finished_summary(run_dir: Path, cfg: DictConfig) -> Summary | None:
    """The stored summary of a finished run whose budget ``cfg`` does not raise (the
    checkpoint's config checked as a resume checks it), else None: resuming it has nothing to
    train, and must not write its summary again (another process may have finished it)."""
    import dataclasses
    import json

    from memrl.checkpoint import resume as ckpt
    from memrl.dqn.loop import Summary

    path = run_dir / "summary.json"
    if not (path.is_file() and (run_dir / "checkpoints" / "final.pt").is_file()):
        return None
    done = json.loads(path.read_text())
    if not budget_reached(cfg, done):
        return None  # a bigger budget: train on from the last checkpoint
    ckpt.load_state(ckpt.find(run_dir), cfg)  # a run of another config is refused, as on resume
    known = {f.name for f in dataclasses.fields(Summary)}
    return Summary(**{k: v for k, v in done.items() if k in known})


def train(cfg: DictConfig, out_dir: Path | None = None,
          demos: TensorDictBase | None = None) -> Summary:
    """Train one run; with ``cfg.resume`` set, continue that run folder from its checkpoint.

    Args:
        cfg: the composed ``train`` config.
        out_dir: run folder (default: Hydra's ``paths.output_dir``); ignored when resuming.
        demos: prior-knowledge transitions to use instead of loading ``mode.demos_path``.
    """
    with opened_run(cfg, out_dir, demos) as opened:
        if not isinstance(opened, tuple):
            return opened  # finished earlier at this budget
        trainer, run_dir = opened
        summary = deferred_run(trainer.run)
    _done(summary, run_dir)
    return summary


def deferred_run(work: Callable[[], T]) -> T:
    """``work()`` with signals deferred (a signal stops at the loop's next checkpoint), a signal's
    stop raised as :class:`Interrupted` even where clean-up code masked it on its way up."""
    with deferred():
        try:
            return work()
        except Exception as err:  # a second signal, raised at once, masked on its way up
            if (stop := interruption(err)) is not None:
                raise Interrupted(stop.signum) from err
            raise


def train_seeds(cfg: DictConfig, seeds: Sequence[int], out_dir: Path | None = None,
                demos: TensorDictBase | None = None) -> list[Summary]:
    """Train ``cfg`` at each of ``seeds`` in this process, their turns in order
    (:mod:`memrl.dqn.seed_group`): run folders ``<out_dir>/s<seed>``, each what that seed's own
    run writes. With ``cfg.resume`` set (the group's folder), every run continues from its own
    checkpoint. Every seed's config is checked before any folder is made."""
    if not seeds or len(set(seeds)) != len(seeds):
        from memrl.errors import config_error

        raise config_error("seeds", f"need distinct seeds, got {list(seeds)}")
    group = Path(cfg.resume) if cfg.resume else Path(out_dir or cfg.paths.output_dir)
    cfgs = []
    for seed in seeds:
        c = cfg.copy()
        c.seed, c.seeds = int(seed), None  # each run's config is its single-seed run's
        if cfg.resume:
            c.resume = str(group / f"s{seed}")
        cfgs.append(c)
    return train_group(cfgs, [group / f"s{seed}" for seed in seeds], demos,
                       shared_engine=str(cfg.seeds_engine) == "shared" and len(cfgs) > 1)


ONE_RUN_LOGGERS = {"WandbLogger": ("wandb", "W&B"), "MLFlowLogger": ("mlflow", "MLflow")}
"""Backends with one active run per process (``wandb.init``, ``mlflow.start_run``)."""


def group_refusal(cfg: DictConfig) -> str | None:
    """Why ``cfg``'s runs cannot share a process (None: they can)."""
    logger = cfg.get("logger")
    if not logger or "_target_" not in logger:
        return None
    target = str(logger["_target_"]).rsplit(".", 1)[-1]
    if target in ONE_RUN_LOGGERS:
        group, backend = ONE_RUN_LOGGERS[target]
        return (f"logger={group} keeps one active run per process ({backend}); train these seeds in "
                "processes of their own, or use logger=tensorboard, csv or none")
    return None


def train_group(cfgs: Sequence[DictConfig], run_dirs: Sequence[Path],
                demos: TensorDictBase | None = None, shared_engine: bool = False) -> list[Summary]:
    """Train the runs ``cfgs`` (each a single run's config: its own seed, ``resume`` its folder
    or null) into ``run_dirs`` in this process, their turns in order
    (:mod:`memrl.dqn.seed_group`); each run writes what its own process writes. Every config is
    checked before any folder is made; a run finished earlier at its budget is only reported.
    ``shared_engine``: the runs' training envs on one engine, stepped together
    (:func:`~memrl.dqn.seed_group.run_lockstep`)."""
    from contextlib import ExitStack

    from memrl.dqn.seed_group import Member, RngState, active_run, run_lockstep, run_turns

    if len(cfgs) != len(run_dirs):
        raise ValueError(f"{len(cfgs)} configs for {len(run_dirs)} run folders")
    for c in cfgs:
        check_train(c)
        if len(cfgs) > 1 and (why := group_refusal(c)):
            from memrl.errors import config_error

            raise config_error("logger", why)
    shared = shared_engine_of(cfgs) if shared_engine else None
    outer = RngState.now()
    members, dirs = [], []
    with ExitStack() as stack:
        for k, (c, run_dir) in enumerate(zip(cfgs, run_dirs, strict=True)):
            with active_run(Path(c.resume) if c.resume else Path(run_dir)):
                opened = stack.enter_context(opened_run(c, Path(run_dir), demos,
                                                        None if shared is None else shared.slices[k]))
            if isinstance(opened, tuple):
                members.append(Member(opened[0], run_dir=opened[1]))  # generators as its Trainer left them
                dirs.append(opened[1])
            else:
                members.append(Member(None, summary=opened, run_dir=Path(opened.run_dir)))
                dirs.append(Path(opened.run_dir))
            outer.restore()  # the next run starts from the same outer state, as its own process
        summaries = deferred_run(
            lambda: run_turns(members) if shared is None else run_lockstep(members, shared))
    for summary, run_dir in zip(summaries, dirs, strict=True):
        with active_run(run_dir):
            _done(summary, run_dir)
    return summaries


def shared_engine_of(cfgs: Sequence[DictConfig]) -> Any:
    """One engine for the training envs of every run of ``cfgs`` (a slice each,
    :class:`~memrl.envs.shared_engine.SharedEngine`), or a one-line refusal naming
    ``seeds_engine``: the runs need the same env config and device, ``env.num_envs`` > 1 and no
    learned cars."""
    from memrl.envs.batched import resolve_device
    from memrl.envs.config import BatchedEnvError
    from memrl.envs.shared_engine import SharedEngine
    from memrl.envs.torchrl_env import env_kwargs
    from memrl.errors import config_error

    first = cfgs[0]
    if int(first.env.num_envs) < 2:
        raise config_error("seeds_engine", "shared needs env.num_envs > 1 (one env per seed runs the "
                           "reference env); use seeds_engine=own")
    for c in cfgs[1:]:
        if OmegaConf.to_container(c.env, resolve=True) != OmegaConf.to_container(first.env, resolve=True) \
                or str(c.device) != str(first.device):
            raise config_error("seeds_engine", "shared needs one env config and device for every seed")
    try:
        return SharedEngine({**env_kwargs(first.env), "frame_stack": 1}, int(first.env.num_envs), len(cfgs),
                            resolve_device(first.device))
    except BatchedEnvError as err:
        raise config_error("seeds_engine", f"shared: {err}") from err


def _done(summary: Summary, run_dir: Path) -> None:
    log.info("done: %d episodes, %d frames, %d updates in %.0f s; summary in %s",
             summary.episodes, summary.frames, summary.updates, summary.wall_s,
             run_dir / "summary.json")


@contextmanager
def opened_run(cfg: DictConfig, out_dir: Path | None = None, demos: TensorDictBase | None = None,
               engine: Any | None = None) -> Iterator[tuple[Trainer, Path] | Summary]:
    """A run made ready to train: its folder claimed and locked, its logger open, its trainer
    built (and resumed) and its provenance recorded; or its stored summary where it finished
    earlier at this budget. The lock and the logger are held for the block. ``engine``: the
    run's slice of a shared engine (:func:`shared_engine_of`)."""
    from memrl.dqn.loop import Trainer  # noqa: F811  (the runtime import; the one above is for types)
    from memrl.loggers import check_backend, open_logger
    from memrl.provenance import auto_precision_change, read_provenance, record_provenance
    from memrl.run_folder import check_start_folder, claim_start_folder
    from memrl.run_lock import run_lock

    check_train(cfg)  # every value, the env config and the named folders, before any write
    check_backend(cfg.get("logger"))
    run_dir = Path(cfg.resume) if cfg.resume else Path(out_dir or cfg.paths.output_dir)
    fresh = not cfg.resume
    overwrite = bool(cfg.get("overwrite", False))
    check_start_folder(run_dir, fresh, overwrite)  # a folder that holds a run: refused
    from memrl.modes import mode_of

    if demos is None and mode_of(cfg).needs_demos:
        demos = prior_knowledge(cfg)  # a bad dataset stops the run before its folder is made
    before = set(run_dir.iterdir()) if run_dir.is_dir() else None
    run_dir.mkdir(parents=True, exist_ok=True)
    with run_lock(run_dir):
        claim_start_folder(run_dir, fresh, overwrite)  # checked again; overwrite=true clears it
        stored = finished_summary(run_dir, cfg) if cfg.resume else None
        if stored is not None:
            log.info("%s finished earlier at this budget (%d frames, %d episodes): nothing to "
                     "train, summary.json kept", run_dir, stored.frames, stored.episodes)
            yield stored
            return
        saved = cfg.copy()
        saved.paths.output_dir = str(run_dir)  # resolvable outside a Hydra run too
        resolved = OmegaConf.to_container(saved, resolve=True)
        assert isinstance(resolved, dict)
        with open_logger(saved, run_dir, hparams=None if cfg.resume else resolved) as logger:
            try:
                if fresh:
                    (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(saved, resolve=True))
                trainer = Trainer(cfg, run_dir, demos, logger, engine)
                if cfg.resume:
                    trainer.resume(run_dir)
            except BaseException:
                if fresh:  # a failed start leaves no folder that looks like a run
                    remove_new_entries(run_dir, before)
                raise
            record_provenance(run_dir, "start" if fresh else "resume")
            if cfg.resume and str(cfg.agent.precision) == "auto" and (
                    change := auto_precision_change(read_provenance(run_dir))):
                log.warning(change)
            yield trainer, run_dir


def train_any(cfg: DictConfig) -> Summary | list[Summary]:
    """One run, or with ``seeds`` set, those seeds in this process (:func:`train_seeds`)."""
    if cfg.get("seeds"):
        return train_seeds(cfg, [int(s) for s in cfg.seeds])
    return train(cfg)


@hydra.main(version_base="1.3", config_path="conf", config_name="train")
def main(cfg: DictConfig) -> None:
    run_task(train_any, cfg)


if __name__ == "__main__":
    register_configs()
    run_hydra(main)
