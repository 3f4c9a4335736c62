"""``python -m memrl.train [+mode=A|B] [+experiment=smoke] [-m] [key=value ...]``."""

from __future__ import annotations

import logging
import traceback
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase

from memrl.cli import run_hydra
from memrl.configs import register_configs
from memrl.dqn.config import check_train_config
from memrl.dqn.loop import Summary, Trainer
from memrl.loggers import check_backend, open_logger
from memrl.run_lock import run_lock

log = logging.getLogger(__name__)


def prior_knowledge(cfg: DictConfig) -> TensorDictBase:
    """The demo transitions of ``mode.demos_path`` (checked against the env config), or the
    cached scripted-driver example dataset when it is null."""
    from memrl.data import demos

    path = cfg.mode.demos_path
    if path is None:
        path = demos.ensure_example_demos(cfg.env, Path(cfg.paths.data_dir))
    return demos.load_demos(Path(path), env_cfg=cfg.env)


def train(cfg: DictConfig, out_dir: Path | None = None,
          demos: TensorDictBase | None = None) -> Summary:
    """Train one run; with ``cfg.resume`` set, continue that run folder from its checkpoint.

    Args:
        cfg: the composed ``train`` config.
        out_dir: run folder (default: Hydra's ``paths.output_dir``); ignored when resuming.
        demos: prior-knowledge transitions to use instead of loading ``mode.demos_path``.
    """
    check_train_config(cfg)
    check_backend(cfg.get("logger"))
    run_dir = Path(cfg.resume) if cfg.resume else Path(out_dir or cfg.paths.output_dir)
    if cfg.resume and not run_dir.is_dir():
        raise FileNotFoundError(f"resume: no run folder {run_dir}")
    run_dir.mkdir(parents=True, exist_ok=True)
    with run_lock(run_dir):
        saved = cfg.copy()
        saved.paths.output_dir = str(run_dir)  # resolvable outside a Hydra run too
        resolved = OmegaConf.to_container(saved, resolve=True)
        assert isinstance(resolved, dict)
        if not cfg.resume:
            (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(saved, resolve=True))
        if demos is None and cfg.mode.name in ("A", "B"):
            demos = prior_knowledge(cfg)
        with open_logger(saved, run_dir, hparams=None if cfg.resume else resolved) as logger:
            trainer = Trainer(cfg, run_dir, demos, logger)
            if cfg.resume:
                trainer.resume(run_dir)
            summary = trainer.run()
    log.info("done: %d episodes, %d frames, %d updates in %.0f s; summary in %s",
             summary.episodes, summary.frames, summary.updates, summary.wall_s,
             run_dir / "summary.json")
    return summary


@hydra.main(version_base="1.3", config_path="../conf", config_name="train")
def main(cfg: DictConfig) -> None:
    try:
        train(cfg)
    except Exception:
        if HydraConfig.get().mode != RunMode.MULTIRUN:
            raise
        # In a sweep, one failing job is recorded and the others go on.
        out = Path(cfg.paths.output_dir)
        out.mkdir(parents=True, exist_ok=True)
        (out / "error.txt").write_text(traceback.format_exc())
        log.exception("job failed; error written to %s", out / "error.txt")


if __name__ == "__main__":
    register_configs()
    run_hydra(main)
