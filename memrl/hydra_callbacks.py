"""Hydra callbacks of every command (``conf/hydra/default.yaml``).

* :class:`StartChecks`: the command's checks (:data:`memrl.schemas.CHECKS`) before Hydra makes
  the run folder, so that bad input leaves nothing behind.
* :class:`SweepFailures`: after a sweep, list the jobs that failed and exit non-zero.
"""

from __future__ import annotations

import os
import sys
import traceback
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from memrl.errors import ONE_LINE_ENV, USAGE_EXIT, is_user_error, one_line

ERROR_FILE = "error.txt"
"""Written into a sweep job's folder when the job fails (:func:`memrl.cli.run_task`)."""

SWEEP_FAILED_EXIT = 1
"""Exit status of a sweep in which some job failed."""


def check_config(config: DictConfig) -> None:
    """Run the checks of the command whose config this is (by config name)."""
    from memrl.schemas import CHECKS, check_writable

    name = OmegaConf.select(config, "hydra.job.config_name")
    check = CHECKS.get(str(name))
    if check is not None:
        check(config)
    run_dir = OmegaConf.select(config, "hydra.run.dir")
    if run_dir is not None:
        check_writable(run_dir, "paths.output_root")  # before Hydra makes the run folder
        remember_start(Path(str(run_dir)))


class Before:
    """What a single run's folder looked like before Hydra wrote into it (recorded by the start
    checks, which run first): the deepest of its folders that existed, and the bytes and times
    of its ``.hydra/*`` files. A refused start puts them back (:func:`memrl.cli.run_task`)."""

    def __init__(self, run_dir: Path) -> None:
        self.run_dir = run_dir.absolute()
        self.existed = existing_ancestor(self.run_dir)
        hydra_dir = self.run_dir / ".hydra"
        self.files = {f: (f.read_bytes(), f.stat()) for f in hydra_dir.iterdir() if f.is_file()} \
            if hydra_dir.is_dir() else {}
        self.logs = set(self.run_dir.glob("*.log"))

    def restore(self) -> None:
        """The ``.hydra/*`` files back as they were (a file Hydra added there goes, and a log it
        started in a folder that existed)."""
        import os

        if self.existed == self.run_dir:  # a log Hydra started in a folder that was there
            for log in set(self.run_dir.glob("*.log")) - self.logs:
                log.unlink()
        hydra_dir = self.run_dir / ".hydra"
        if not self.files or not hydra_dir.is_dir():
            return
        for f in hydra_dir.iterdir():
            if f.is_file() and f not in self.files:
                f.unlink()
        for f, (data, st) in self.files.items():
            f.write_bytes(data)
            os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns))


STARTS: dict[Path, Before] = {}
"""Run folder -> :class:`Before`, for the single runs this process started."""


def remember_start(run_dir: Path) -> None:
    STARTS[run_dir.absolute()] = Before(run_dir)


def before_start(run_dir: Path) -> Before | None:
    """What :func:`remember_start` recorded for ``run_dir`` (None: not started here)."""
    return STARTS.get(run_dir.absolute())


def existing_ancestor(path: Path) -> Path:
    """``path`` or its deepest ancestor that exists."""
    path = path.absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def sweep_jobs(config: DictConfig) -> list[list[str]]:
    """The overrides of every job of a sweep, in the basic sweeper's order (its cartesian
    product of the ``a=1,2`` sweeps and ``hydra.sweeper.params``)."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    params = OmegaConf.select(config, "hydra.sweeper.params") or {}
    args = [f"{k}={v}" for k, v in params.items()] + list(config.hydra.overrides.task)
    parsed = OverridesParser.create().parse_overrides(args)
    return [list(job) for batch in BasicSweeper.split_arguments(parsed, None) for job in batch]


def check_sweep(config: DictConfig) -> None:
    """Compose and check every job's config before any job starts (or the sweep folder is
    made); the first bad job is named with its overrides."""
    from hydra.core.global_hydra import GlobalHydra
    from omegaconf import open_dict

    from memrl.errors import UserError
    from memrl.schemas import CHECKS, check_writable

    check = CHECKS.get(str(OmegaConf.select(config, "hydra.job.config_name")))
    loader = GlobalHydra.instance().config_loader()
    for num, job in enumerate(sweep_jobs(config)):
        if check is None:
            break
        job_cfg = loader.load_sweep_config(config, job)
        with open_dict(job_cfg):  # as the launcher sets it: the job's folder (hydra.sweep.subdir)
            job_cfg.hydra.job.num = num
        try:
            check(job_cfg)
        except Exception as err:
            if not is_user_error(err):
                raise
            raise UserError(f"job {num} [{' '.join(job)}]: {one_line(err)}") from None
    check_writable(str(config.hydra.sweep.dir), "paths.output_root")


def _stop(config: DictConfig, err: Exception) -> None:
    # Hydra turns a callback's exception into a warning and goes on: stop here instead.
    if is_user_error(err) and os.environ.get(ONE_LINE_ENV) and not config.get("debug"):
        print(f"error: {one_line(err)}", file=sys.stderr)
        sys.exit(USAGE_EXIT)
    traceback.print_exc()
    sys.exit(USAGE_EXIT if is_user_error(err) else 1)


class StartChecks(Callback):
    """Check a single run's config before its folder exists (Hydra calls this first), and
    every job's config of a sweep before any job is launched."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        try:
            check_config(config)
        except Exception as err:
            _stop(config, err)

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        try:
            check_sweep(config)
        except Exception as err:
            _stop(config, err)


def failed_jobs(sweep_dir: Path) -> tuple[int, list[Path]]:
    """The number of job folders of a sweep and the error files of those that failed."""
    # job folders: not hidden ones such as a launcher's own (.submitit)
    jobs = [p for p in sweep_dir.iterdir() if p.is_dir() and not p.name.startswith(".")] \
        if sweep_dir.is_dir() else []
    return len(jobs), sorted((p / ERROR_FILE for p in jobs if (p / ERROR_FILE).is_file()),
                             key=lambda p: (len(p.parent.name), p.parent.name))


def _overrides(job_dir: Path) -> str:
    """The job's own overrides, from Hydra's record of them (``.hydra/overrides.yaml``)."""
    file = job_dir / ".hydra" / "overrides.yaml"
    if not file.is_file():
        return ""
    return " ".join(str(o) for o in OmegaConf.load(file))


def failure_report(sweep_dir: Path) -> str | None:
    """Lines naming each failed job, its overrides and its error file (None: all passed)."""
    total, errors = failed_jobs(sweep_dir)
    if not errors:
        return None
    lines = [f"sweep: {len(errors)} of {total} jobs failed ({sweep_dir}):"]
    for err in errors:
        last = err.read_text().strip().splitlines()[-1:] or [""]
        lines.append(f"  job {err.parent.name} [{_overrides(err.parent)}]: {last[0]} -> {err}")
    return "\n".join(lines)


class SweepFailures(Callback):
    """After every job of a sweep ran, report the failed ones and exit non-zero."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        report = failure_report(Path(str(config.hydra.sweep.dir)))
        if report is not None:
            # Hydra's launchers return the jobs' results but its multirun discards them.
            print(report, file=sys.stderr)
            sys.exit(SWEEP_FAILED_EXIT)
