"""Command-line helpers shared by the ``@hydra.main`` entry points."""

from __future__ import annotations

import logging
import os
import shutil
import sys
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from memrl.errors import ONE_LINE_ENV, USAGE_EXIT, is_user_error, one_line
from memrl.stop import Interrupted, Stopped, install, output_overrides

log = logging.getLogger(__name__)

_FLAGS_FIRST = ("-m", "--multirun")
_DEBUG_ON = ("true", "True", "1", "yes")
HYDRA_FILES = (".hydra",)
"""What Hydra itself puts into a run folder before the task starts (besides ``<task>.log``)."""


def normalize_argv(argv: Sequence[str], positional_key: str | None = None) -> list[str]:
    """Let users put Hydra's flags anywhere and name sub-commands by bare words.

    Plain Hydra rejects ``-m`` after an override (``python -m memrl.train +mode=B -m seed=0,1``);
    this moves ``-m``/``--multirun`` to the front. Bare words (no ``=``, not a flag) become
    ``positional_key=[word, ...]`` when a key is given, e.g. ``bench env`` -> ``benchmarks=[env]``.
    """
    args = list(argv)
    flags = [a for a in args if a in _FLAGS_FIRST]
    rest = [a for a in args if a not in _FLAGS_FIRST]
    words: list[str] = []
    if positional_key is not None:
        # A bare word directly after a flag that takes a value is that flag's value.
        takes_value = {"--cfg", "-c", "--config-name", "-cn", "--config-path", "-cp", "--config-dir",
                       "-cd", "--info", "-i", "--package", "-p", "--experimental-rerun"}
        kept: list[str] = []
        for i, a in enumerate(rest):
            prev = rest[i - 1] if i else ""
            if "=" not in a and not a.startswith("-") and prev not in takes_value:
                words.append(a)
            else:
                kept.append(a)
        rest = kept
    if words:
        rest.append(f"{positional_key}=[{','.join(words)}]")
    return flags + rest


def wants_traceback(argv: Sequence[str]) -> bool:
    """``debug=true`` on the command line, or ``HYDRA_FULL_ERROR=1`` in the environment."""
    debug = any(a.lstrip("+").split("=", 1) in (["debug", v] for v in _DEBUG_ON) for a in argv)
    return debug or os.environ.get("HYDRA_FULL_ERROR") in _DEBUG_ON


HELP_FLAGS = ("--help", "-h", "--hydra-help")


def share_group_listing() -> None:
    """Make Hydra's help screen list the config groups from one copy of its repository.

    Hand-written: Hydra 1.3 deep-copies the whole config repository (every structured schema)
    for each of the ~120 group look-ups of ``--help``, 2-5 s here; they all read the same one.
    Composition is untouched (it does not go through ``get_group_options``).
    """
    from hydra._internal.config_loader_impl import ConfigLoaderImpl
    from hydra.core.object_type import ObjectType

    repos: dict[tuple, Any] = {}

    def get_group_options(self: Any, group_name: str,
                          results_filter: ObjectType | None = ObjectType.CONFIG,
                          config_name: str | None = None,
                          overrides: list[str] | None = None) -> list[str]:
        key = (id(self), config_name, tuple(overrides or ()))
        if key not in repos:
            repos[key] = self._parse_overrides_and_create_caching_repo(config_name,
                                                                        list(overrides or ()))[1]
        return repos[key].get_group_options(group_name, results_filter)

    ConfigLoaderImpl.get_group_options = get_group_options  # type: ignore[method-assign]


def run_hydra(main: Callable[[], Any], positional_key: str | None = None) -> Any:
    """Call a ``@hydra.main`` function after :func:`normalize_argv` on ``sys.argv``.

    A user error (:func:`memrl.errors.is_user_error`) prints one line and exits with
    :data:`~memrl.errors.USAGE_EXIT`; other errors keep their full traceback. With
    ``debug=true`` or ``HYDRA_FULL_ERROR=1``, every error shows its full traceback.
    """
    sys.argv = [sys.argv[0], *normalize_argv(sys.argv[1:], positional_key)]
    one_line_errors = not wants_traceback(sys.argv[1:])
    if any(a in HELP_FLAGS for a in sys.argv[1:]):
        share_group_listing()
    # Hand-written: Hydra prints its own multi-line trace for every error; with
    # HYDRA_FULL_ERROR it raises instead, and the user errors get one line here.
    install()  # SIGINT / SIGTERM: a clean stop with the resume command (memrl.stop)
    saved = {k: os.environ.get(k) for k in ("HYDRA_FULL_ERROR", ONE_LINE_ENV)}
    os.environ["HYDRA_FULL_ERROR"] = "1"
    if one_line_errors:
        os.environ[ONE_LINE_ENV] = "1"
    try:
        return main()
    except Interrupted as stop:  # before the task started (composition, checks, Hydra's files)
        print(interrupted_before_task(stop), file=sys.stderr)
        sys.exit(stop.exit_status)
    except Exception as err:
        if not (one_line_errors and is_user_error(err)):
            raise
        print(f"error: {one_line(err)}", file=sys.stderr)
        sys.exit(USAGE_EXIT)
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def interrupted_before_task(stop: Interrupted) -> str:
    """The line for a signal that came before :func:`run_task` took over: during composition
    and the start checks (nothing made: ``interrupted by SIGTERM``), or once Hydra had made the
    run folder (``.hydra/``, the log), which is then handled as a stop before the first
    checkpoint (:func:`stopped_line`: the new folder is removed, the command printed)."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode
    from omegaconf import OmegaConf

    cfg = HydraConfig.instance().cfg
    where = OmegaConf.select(cfg, "hydra.runtime.output_dir", default=None) if cfg is not None else None
    if where is None or not Path(str(where)).is_dir() or \
            OmegaConf.select(cfg, "hydra.mode", default=None) == RunMode.MULTIRUN:
        return f"interrupted by {stop.name}"
    overrides = [str(o) for o in OmegaConf.select(cfg, "hydra.overrides.task", default=[]) or []]
    return stopped_line(stop, cfg, Path(str(where)), overrides)  # type: ignore[arg-type]


def remove_if_bare(run_dir: Path) -> bool:
    """Remove a run folder that holds only what Hydra wrote before the task (True if removed),
    and the folders Hydra made above it that are left empty (``outputs/deploy/runs/``). A
    folder that existed before this run is kept, its ``.hydra/`` files put back as they were."""
    from memrl.hydra_callbacks import before_start

    if not run_dir.is_dir():
        return False
    if any(p.name not in HYDRA_FILES and p.suffix != ".log" for p in run_dir.iterdir()):
        return False
    before = before_start(run_dir)
    if before is not None and before.existed == run_dir.absolute():
        before.restore()
        return False
    shutil.rmtree(run_dir, ignore_errors=True)
    if before is not None:  # the empty folders Hydra made above it
        folder = run_dir.absolute().parent
        while folder != before.existed and before.existed in folder.parents and folder.is_dir() \
                and not any(folder.iterdir()):
            folder.rmdir()
            folder = folder.parent
    return True


def undo_hydra_files(out: Path, subdir: str | None, log_file: Path, log_stat: os.stat_result | None,
                     ) -> None:
    """Take back what Hydra wrote for a refused start into a folder that existed before it (a
    resumed run, a study): its own ``.hydra/<time>/`` record, and the log lines of this call."""
    if subdir and Path(subdir).parts[:1] == (".hydra",) and len(Path(subdir).parts) > 1:
        shutil.rmtree(out / subdir, ignore_errors=True)
        if (out / ".hydra").is_dir() and not any((out / ".hydra").iterdir()):
            (out / ".hydra").rmdir()
    if log_stat is not None and log_file.is_file():
        with log_file.open("r+b") as f:
            f.truncate(log_stat.st_size)
        os.utime(log_file, ns=(log_stat.st_atime_ns, log_stat.st_mtime_ns))


def run_task(task: Callable[[DictConfig], Any], cfg: DictConfig) -> Any:
    """The body of every ``@hydra.main``: call the typed function ``task`` on ``cfg``.

    A single run that fails leaves no folder that looks like a run (Hydra's own files are
    removed). In a sweep, a failing job writes its traceback to ``error.txt`` in its folder and
    the sweep goes on; ``memrl.hydra_callbacks.SweepFailures`` reports it at the end.
    """
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    from memrl.hydra_callbacks import ERROR_FILE
    hydra_cfg = HydraConfig.get()
    out = Path(hydra_cfg.runtime.output_dir)
    log_file = out / f"{cfg.get('task_name') or hydra_cfg.job.name}.log"
    log_stat = log_file.stat() if log_file.is_file() else None
    try:
        return task(cfg)
    except Interrupted as stop:
        print(stopped_line(stop, cfg, out, list(hydra_cfg.overrides.task)), file=sys.stderr)
        sys.exit(stop.exit_status)
    except Stopped as err:  # ended early on request (Esc, Ctrl-C, SIGTERM): one line, its status
        remove_if_bare(out)
        print(str(err), file=sys.stderr)
        sys.exit(err.status)
    except Exception as err:
        if hydra_cfg.mode != RunMode.MULTIRUN:
            if is_user_error(err):
                undo_hydra_files(out, hydra_cfg.output_subdir, log_file, log_stat)
                from memrl.hydra_callbacks import before_start

                if (before := before_start(out)) is not None:
                    before.restore()  # a folder that existed: its .hydra/*.yaml as they were
            remove_if_bare(out)
            if is_user_error(err) and os.environ.get(ONE_LINE_ENV):
                # here, not in run_hydra: Hydra would first print a line of its own
                print(f"error: {one_line(err)}", file=sys.stderr)
                sys.exit(USAGE_EXIT)
            raise
        out.mkdir(parents=True, exist_ok=True)
        (out / ERROR_FILE).write_text(traceback.format_exc())
        summary = one_line(err) if is_user_error(err) else f"{type(err).__name__}: {err}"
        log.error("job failed: %s; traceback in %s", summary, out / ERROR_FILE)
        return None


def stopped_line(stop: Interrupted, cfg: DictConfig, out: Path, overrides: list[str]) -> str:
    """The one line printed when a signal stopped a command: what was kept and the exact
    command that continues it (train: ``resume=<run folder>``; the others: the same command,
    which reuses what is finished). A new training run stopped before its first checkpoint has
    nothing to resume: its folder is removed."""
    import shlex

    overrides = [*overrides, *(o for o in output_overrides() if o not in overrides)]  # hydra.run.dir
    task = str(cfg.get("task_name", "train"))
    if task == "train":
        from memrl.checkpoint import resume as ckpt

        try:
            ckpt.find(out)
        except ckpt.CheckpointError:
            if not cfg.get("resume"):
                shutil.rmtree(out, ignore_errors=True)
            again = shlex.join(["python", "-m", "memrl.train", *overrides])
            return f"interrupted by {stop.name} before the first checkpoint: nothing to resume; " \
                   f"start again with: {again}"
        args = [o for o in overrides if o.split("=", 1)[0].lstrip("+") != "resume"]
        command = shlex.join(["python", "-m", "memrl.train", *args, f"resume={out}"])
        return f"interrupted by {stop.name}: checkpoint kept in {out / 'checkpoints'}; " \
               f"resume with: {command}"
    command = shlex.join(["python", "-m", f"memrl.{task}", *overrides])
    if task == "study":  # the same command skips finished runs and resumes the others
        return f"interrupted by {stop.name}: finished runs and checkpoints kept; continue with: {command}"
    remove_if_bare(out)  # nothing finished: no empty output folder
    return f"interrupted by {stop.name}: nothing written; run again with: {command}"
