"""The study's grid: one training run per (variant, mode, opponent, seed), composed, resumed,
trained.

Each cell is trained by calling :func:`memrl.train.train` on the train config composed with
Hydra's compose API (the user's ``study.train_overrides``, its variant's overrides from
``study.variants``, a ``mode.<key>`` one only for the modes that have that key, then the
cell's mode, opponent, seed and variant name), in this process
(``study.jobs=1``) or in ``study.jobs`` spawned processes, one cell per process or, with
``study.seeds_per_process=K``, up to K seeds of one configuration per process
(:func:`memrl.train.train_group`). Why not Hydra's launcher: every cell
needs its own decision first (skip a finished run, ``resume=`` a killed one, start a new one),
and the study evaluates each run as it finishes (``study.evaluate``) and reports once all
cells are done; a sweep of the train app decides neither.
"""

from __future__ import annotations

import logging
import shutil
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from contextlib import contextmanager
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

import memrl
from memrl.modes import by_label
from memrl.stop import Interrupted
from memrl.workers import stopped_with_parent, worker_start

log = logging.getLogger(__name__)

CONF_DIR = str(memrl.CONF_DIR)
CELL_DEFAULTS = ["progress=false"]
"""Overrides of every cell before the user's (no progress bars from parallel runs)."""


def compose_config(name: str, overrides: Sequence[str]) -> DictConfig:
    """``conf/<name>.yaml`` composed with ``overrides`` (inside a Hydra app or outside one)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from memrl.configs import register_configs

    register_configs()
    if GlobalHydra.instance().is_initialized():  # inside @hydra.main: the app's search path
        return compose(config_name=name, overrides=list(overrides))
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name=name, overrides=list(overrides))


@dataclass
class Cell:
    """One training run of the grid."""

    mode: str
    opponent: str
    seed: int
    run_dir: Path
    overrides: list[str]
    cfg: DictConfig | None = None
    """The composed train config (``paths.output_dir`` set to ``run_dir``)."""
    variant: str | None = None
    """Its name in ``study.variants`` (None: the study has no variants)."""

    @property
    def name(self) -> str:
        return self.run_dir.name

    @property
    def label(self) -> str:
        """Its Table III row: ``B``, ``B (mixed)``, ``B (cue)``, ``B (cue, mixed)``."""
        from memrl.evaluation.rows import row_label

        return row_label(self.mode, self.opponent, self.variant)

    def finished(self) -> bool:
        """``summary.json`` and ``checkpoints/final.pt``: nothing left to train."""
        return (self.run_dir / "summary.json").is_file() and \
            (self.run_dir / "checkpoints" / "final.pt").is_file()

    def resumable(self) -> bool:
        """Killed after a checkpoint: resume from it."""
        return not self.finished() and (self.run_dir / "checkpoints" / "last").is_dir()


def cell_name(mode: str, traffic: str, seed: int, variant: str | None = None) -> str:
    """A run's folder name: ``B_constant_s0``, with variants ``cue_B_constant_s0``."""
    return (f"{variant}_" if variant else "") + f"{mode}_{traffic}_s{seed}"


def cells(study: DictConfig, runs_dir: Path) -> list[Cell]:
    """The grid, composed (a bad train override stops here, naming the key)."""
    out = []
    opponents: list[str | None] = [str(o) for o in study.opponents] or [None]
    variants: dict[str | None, list[str]] = {
        str(k): [str(o) for o in v] for k, v in (study.get("variants") or {}).items()} or {None: []}
    user = [str(o) for o in study.train_overrides]
    for variant, extra in variants.items():
        for mode in study.modes:
            for opponent in opponents:
                for seed in study.seeds:
                    spec = by_label(str(mode))
                    grid = [*spec.overrides, *([f"opponent={opponent}"] if opponent else []),
                            f"seed={int(seed)}", *([f"variant='{variant}'"] if variant else [])]
                    # the user's and the variant's mode keys go to the modes that have them
                    overrides = [*CELL_DEFAULTS, *spec.own_overrides([*user, *extra]), *grid]
                    cfg = compose_config("train", overrides)
                    traffic = str(cfg.env.opponent.type)
                    run_dir = runs_dir / cell_name(str(mode), traffic, int(seed), variant)
                    cfg.paths.output_dir = str(run_dir)  # resolvable outside a Hydra run
                    out.append(Cell(str(mode), traffic, int(seed), run_dir, overrides, cfg, variant))
    return out


@dataclass
class Outcome:
    """What happened to the cells."""

    skipped: list[str] = field(default_factory=list)
    """Finished before this call."""
    trained: list[str] = field(default_factory=list)
    """Started and finished now."""
    resumed: list[str] = field(default_factory=list)
    """Continued from a checkpoint and finished now."""
    failed: dict[str, str] = field(default_factory=dict)
    """Cell -> the error's last line."""


def train_cell(cfg: DictConfig, run_dir: str, resume: bool) -> dict[str, Any]:
    """Train (or resume) one cell; its log goes to ``<run>/train.log``. Runs in a worker
    process too, so it takes and returns plain values."""
    return train_cells([cfg], [run_dir], [resume])[0]


def train_cells(cfgs: Sequence[DictConfig], run_dirs: Sequence[str],
                resumes: Sequence[bool]) -> list[dict[str, Any]]:
    """Train (or resume) cells in this process: one with :func:`memrl.train.train`, several (the
    seeds of one configuration, ``study.seeds_per_process``) with
    :func:`memrl.train.train_group`, on one shared engine where their ``seeds_engine`` is
    ``shared``), each run writing what its own process writes and its log
    lines going to its own ``<run>/train.log``. Takes and returns plain values (worker processes)."""
    import dataclasses

    from memrl.train import train, train_group

    paths = [Path(r) for r in run_dirs]
    runs = []
    for cfg, path, resume in zip(cfgs, paths, resumes, strict=True):
        path.mkdir(parents=True, exist_ok=True)
        cfg = cfg.copy()
        cfg.resume = str(path) if resume else None
        runs.append(cfg)
    where = paths[0] if len(paths) == 1 else ", ".join(map(str, paths))
    with run_logs(paths):
        try:
            if len(runs) == 1:
                return [dataclasses.asdict(train(runs[0], paths[0]))]
            shared = str(runs[0].seeds_engine) == "shared"  # study.train_overrides=[seeds_engine=shared]
            return [dataclasses.asdict(s) for s in train_group(runs, paths, shared_engine=shared)]
        except (Interrupted, KeyboardInterrupt) as stop:  # asked for: no failure, no traceback
            log.info("training %s: %s; its checkpoint is kept", where, stop or "stopped by Ctrl-C")
            raise
        except BaseException:
            log.exception("training %s failed", where)  # the traceback into the runs' train.log
            raise


class _OwnRun(logging.Filter):
    """Passes the lines of its run's turns and those outside any run's turn (a group's own)."""

    def __init__(self, run_dir: Path) -> None:
        super().__init__()
        self.run_dir = run_dir

    def filter(self, record: logging.LogRecord) -> bool:
        from memrl.dqn.seed_group import current_run

        now = current_run()
        return now is None or now == self.run_dir


@contextmanager
def run_logs(paths: Sequence[Path]) -> Iterator[None]:
    """Each run's lines into its ``train.log`` for the block, INFO and up.
    Hand-written: outside a Hydra run nothing writes a run's train.log (Hydra's job_logging)."""
    fmt = logging.Formatter("[%(asctime)s][%(name)s][%(levelname)s] - %(message)s")
    handlers = []
    for path in paths:
        handler = logging.FileHandler(path / "train.log")
        handler.setFormatter(fmt)
        if len(paths) > 1:
            handler.addFilter(_OwnRun(path))
        handlers.append(handler)
    root = logging.getLogger()
    for handler in handlers:
        root.addHandler(handler)
    level = root.level
    root.setLevel(min(level, logging.INFO) if level else logging.INFO)
    try:
        yield
    finally:
        for handler in handlers:
            root.removeHandler(handler)
            handler.close()
        root.setLevel(level)


def _last_line(err: BaseException) -> str:
    return f"{type(err).__name__}: {str(err).strip().splitlines()[-1] if str(err).strip() else ''}"


def plan(grid: Sequence[Cell], out: Outcome) -> list[tuple[Cell, bool]]:
    """The cells to train and whether each resumes; finished ones go to ``out.skipped``. A
    folder without a checkpoint (killed before its first one) is removed and started afresh."""
    todo: list[tuple[Cell, bool]] = []
    for cell in grid:
        if cell.finished():
            out.skipped.append(cell.name)
            continue
        resume = cell.resumable()
        if not resume and cell.run_dir.exists():
            log.info("%s: no checkpoint to resume from; starting it again", cell.name)
            shutil.rmtree(cell.run_dir)
        log.info("%s %s (%s)", "resuming" if resume else "training", cell.name, " ".join(cell.overrides))
        todo.append((cell, resume))
    return todo


def process_groups(todo: Sequence[tuple[Cell, bool]], per_process: int) -> list[list[tuple[Cell, bool]]]:
    """The cells to train, ``per_process`` at most per process: consecutive seeds of one
    (variant, mode, opponent) share one, in the grid's order (1: each cell its own)."""
    from itertools import groupby

    out: list[list[tuple[Cell, bool]]] = []
    for _, same in groupby(todo, key=lambda cr: (cr[0].variant, cr[0].mode, cr[0].opponent)):
        items = list(same)
        out += [items[i:i + per_process] for i in range(0, len(items), max(1, per_process))]
    return out


GroupTrainer = Callable[[Sequence[DictConfig], Sequence[str], Sequence[bool]], list[dict[str, Any]]]


def run_cells(grid: Sequence[Cell], jobs: int,
              trainer: Callable[[DictConfig, str, bool], dict[str, Any]] = train_cell,
              finished: Callable[[Cell], None] | None = None, per_process: int = 1,
              group_trainer: GroupTrainer = train_cells) -> Outcome:
    """Train every unfinished cell (:func:`plan`), ``jobs`` processes at once, each training one
    cell with ``trainer`` or up to ``per_process`` seeds of one configuration with
    ``group_trainer`` (:func:`process_groups`); a failing process fails its unfinished cells and
    the others go on. ``finished`` is called here, in this process, with each cell as it
    finishes (in the order their processes end; the others train on meanwhile). The outcome's
    lists keep the grid's order."""
    out = Outcome()
    units = process_groups(plan(grid, out), per_process)

    def done(unit: list[tuple[Cell, bool]], error: BaseException | None) -> None:
        for cell, resume in unit:
            if error is None or (len(unit) > 1 and cell.finished()):  # it finished before the error
                (out.resumed if resume else out.trained).append(cell.name)
                log.info("%s finished", cell.name)
                if finished is not None:
                    finished(cell)
            else:
                out.failed[cell.name] = _last_line(error)
                log.error("%s failed: %s (log: %s)", cell.name, out.failed[cell.name],
                          cell.run_dir / "train.log")

    def submit(call: Callable[..., Any], unit: list[tuple[Cell, bool]]) -> Any:
        if len(unit) == 1:
            cell, resume = unit[0]
            return call(trainer, cell.cfg, str(cell.run_dir), resume)
        return call(group_trainer, [c.cfg for c, _ in unit], [str(c.run_dir) for c, _ in unit],
                    [r for _, r in unit])

    if jobs <= 1 or len(units) <= 1:
        for unit in units:
            error: BaseException | None = None
            try:
                submit(lambda f, *a: f(*a), unit)
            except Exception as err:  # one failing run must not stop the study
                error = err
            done(unit, error)
    else:  # spawn: a fresh interpreter per worker (no forked torch / OpenMP state)
        with ProcessPoolExecutor(max_workers=jobs, mp_context=get_context("spawn"),
                                 initializer=worker_start) as pool, stopped_with_parent(pool):
            futures: dict[Future, list[tuple[Cell, bool]]] = {submit(pool.submit, u): u for u in units}
            for fut in as_completed(futures):
                done(futures[fut], fut.exception())
    order = {c.name: i for i, c in enumerate(grid)}
    out.trained.sort(key=order.__getitem__)
    out.resumed.sort(key=order.__getitem__)
    out.failed = {k: out.failed[k] for k in sorted(out.failed, key=order.__getitem__)}
    return out
