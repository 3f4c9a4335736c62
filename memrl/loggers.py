"""The run's TorchRL logger (``logger`` group): built, named, fed in step with checkpoints, closed.

One x-axis: ``episode/``, ``train/`` and ``eval/`` points are logged at the run's env steps;
``stage1/`` points (mode B stage 1, which takes no env step) at stage-1 updates. The resolved
config goes to the backend as flat hyperparameters when a run starts (not again on resume).
"""

from __future__ import annotations

import importlib.util
import json
import logging
import os
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig

from memrl.errors import UserError

log = logging.getLogger(__name__)

BACKENDS = {"TensorboardLogger": ("tensorboard", "tensorboard"), "WandbLogger": ("wandb", "wandb"),
            "MLFlowLogger": ("mlflow", "mlflow")}
"""TorchRL logger class -> (package it imports, memrl's pip extra that installs it)."""

RUN_REF = "logger.json"
"""File under ``<run>/logs/`` with the backend's run id, so a resume continues the same run."""


class LoggerBackendMissing(UserError, ImportError):
    """The chosen logger's package is not installed."""


def check_backend(logger_cfg: Mapping[str, Any] | None) -> None:
    """Refuse, in one line naming the extra, a logger whose package is not installed."""
    if not logger_cfg or "_target_" not in logger_cfg:
        return
    cls = str(logger_cfg["_target_"]).rsplit(".", 1)[-1]
    package, extra = BACKENDS.get(cls, (None, None))
    if package is not None and importlib.util.find_spec(package) is None:
        raise LoggerBackendMissing(
            f"logger {cls} needs the '{package}' package: pip install -e \".[{extra}]\" "
            "(or choose logger=csv)")


def flat_hparams(config: Mapping[Any, Any], prefix: str = "") -> dict[str, bool | int | float | str]:
    """A nested config as ``{"agent.lr": 0.00025, ...}`` with scalar values only.

    Hand-written: TensorBoard's hparams and MLflow's params take a flat dict of scalars
    (lists become their string form, null becomes ``"null"``)."""
    out: dict[str, bool | int | float | str] = {}
    for key, value in config.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(flat_hparams(value, f"{name}."))
        elif isinstance(value, bool | int | float | str):
            out[name] = value
        else:
            out[name] = "null" if value is None else json.dumps(value)
    return out


def run_name(run_dir: Path, output_root: Path) -> str:
    """The run folder as the backend's run name: its path under ``paths.output_root``
    (``train/runs/<time>``, ``train/multiruns/<time>/<job>``), else its folder name."""
    run, root = run_dir.resolve(), output_root.resolve()
    return run.relative_to(root).as_posix() if run.is_relative_to(root) else run.name


def make_logger(logger_cfg: DictConfig | None, run_dir: Path, name: str,
                resume: bool = False) -> Any | None:
    """The TorchRL logger of the ``logger`` group writing under ``<run>/logs`` (None for
    ``logger=none``). W&B and MLflow runs are named ``name``; on resume they continue the run
    recorded in ``logs/logger.json``."""
    if not logger_cfg or "_target_" not in logger_cfg:
        return None
    check_backend(logger_cfg)
    cls = str(logger_cfg._target_).rsplit(".", 1)[-1]
    ref_file = run_dir / "logs" / RUN_REF
    ref = json.loads(ref_file.read_text()) if resume and ref_file.exists() else {}
    kwargs: dict[str, Any] = {"log_dir": str(run_dir / "logs")}
    if cls == "WandbLogger":
        kwargs.update(exp_name=name, id=ref.get("id"))
    if cls == "MLFlowLogger" and ref.get("id"):
        os.environ["MLFLOW_RUN_ID"] = ref["id"]  # mlflow.start_run continues that run
    try:
        logger = hydra.utils.instantiate(logger_cfg, **kwargs)
    finally:
        os.environ.pop("MLFLOW_RUN_ID", None)
    run_id = None
    if cls == "WandbLogger":
        run_id = logger.experiment.id
    elif cls == "MLFlowLogger":
        import mlflow

        run_id = logger.experiment.info.run_id
        if not resume:
            mlflow.set_tag("mlflow.runName", name)
    if run_id is not None:
        ref_file.parent.mkdir(parents=True, exist_ok=True)
        ref_file.write_text(json.dumps({"backend": cls, "id": run_id}) + "\n")
    return logger


def close_logger(logger: Any | None) -> None:
    """Flush and end the backend's run (W&B ``finish``, MLflow ``end_run``, files closed)."""
    if logger is None:
        return
    logger.shutdown()
    if type(logger).__name__ == "MLFlowLogger":
        import mlflow

        mlflow.end_run()


@contextmanager
def open_logger(cfg: DictConfig, run_dir: Path, hparams: Mapping[Any, Any] | None
                ) -> Iterator[Any | None]:
    """The run's logger for the duration of the block; ``hparams`` (the resolved config, or
    None on resume) are logged once at the start."""
    logger = make_logger(cfg.get("logger"), run_dir,
                         run_name(run_dir, Path(str(cfg.paths.output_root))),
                         resume=bool(cfg.get("resume")))
    try:
        if logger is not None and hparams is not None:
            logger.log_hparams(flat_hparams(hparams))
        yield logger
    finally:
        close_logger(logger)


class HeldLog:
    """Holds logger points until the checkpoint that covers them is written.

    Hand-written: TorchRL's backends append and cannot take points back (TensorBoard event
    files, W&B and MLflow histories), so the points made after the last checkpoint, which a
    resumed run redoes, must not reach them before a checkpoint does. Each backend then gets
    every point once, as in an uninterrupted run.
    """

    def __init__(self, logger: Any) -> None:
        self.logger = logger
        self.pending: list[tuple[str, float, int]] = []

    def log_scalar(self, name: str, value: float, step: int) -> None:
        self.pending.append((name, float(value), int(step)))

    def flush(self) -> None:
        """Hand the held points to the backend (called right after each checkpoint): one
        ``log_metrics`` call per run of points at the same step (one W&B row, one MLflow
        batch), a repeated name starting the next call."""
        group: dict[str, float] = {}
        for i, (name, value, step) in enumerate(self.pending):
            group[name] = value
            after = self.pending[i + 1] if i + 1 < len(self.pending) else None
            if after is None or after[2] != step or after[0] in group:
                self.logger.log_metrics(group, step=step)
                group = {}
        self.pending.clear()
        self.logger.flush()
