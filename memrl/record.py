"""``python -m memrl.record``: record prior-knowledge datasets (scripted driver or a person)."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import hydra
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from memrl.cli import run_hydra, run_task
from memrl.configs import register_configs
from memrl.schemas import check_record

log = logging.getLogger(__name__)


@dataclass
class RecordSummary:
    """What a recording produced."""

    path: Path | None
    """The dataset folder (None when no episode was kept)."""
    recorded: dict[str, Any]
    """Counts and survival/goal over all recorded episodes (see ``recording.summarize``)."""
    kept: dict[str, Any]
    """The same over the kept episodes (those saved)."""
    seconds: float
    """Wall-clock time of the command [s]."""
    bytes: int
    """Dataset size on disk [bytes]."""
    stopped_early: bool = False


def _figures(stats: dict[str, Any]) -> str:
    n = stats["episodes"]
    return (f"{n} episodes, {stats['transitions']} transitions: survival {stats['survival']}/{n}, "
            f"goal {stats['goal']}/{n}, mean return {stats['mean_return']:.1f}")


def record(cfg: DictConfig) -> RecordSummary:
    """Record ``cfg.episodes`` episodes of ``cfg.demos.policy`` into a dataset and report.

    With ``cfg.example``, make or check the cached scripted example for ``cfg.env`` instead.
    """
    from memrl.data.demos import dataset_bytes, read_metadata
    from memrl.data.recording import ensure_example_demos, record_to_dataset

    check_record(cfg)  # every value, and the output folder writable, before recording
    tail = cfg.get("tail_steps")
    noise = cfg.get("action_noise", 0.0)
    start = time.perf_counter()
    started = datetime.now(UTC).replace(microsecond=0)
    stopped = False
    if cfg.example:
        path: Path | None = ensure_example_demos(cfg.env, cfg.paths.data_dir, cfg.recipe,
                                                 overwrite=bool(cfg.overwrite),
                                                 progress=bool(cfg.progress))
        meta = read_metadata(path)  # type: ignore[arg-type]
        stats = meta["stats"]
        made = datetime.fromisoformat(meta["created"])
        print(f"example dataset {'recorded now' if made >= started else 'from the cache'}: {path}")
    else:
        policy = instantiate(cfg.demos.policy)
        path, rec = record_to_dataset(
            cfg.env, policy, cfg.out, episodes=int(cfg.episodes), seed=int(cfg.seed),
            keep_stable=cfg.keep == "stable", tail_steps=tail, action_noise=float(noise),
            source=str(cfg.demos.source), render=bool(getattr(policy, "needs_render", False)),
            progress=bool(cfg.progress), overwrite=bool(cfg.overwrite),
            extra={"policy": OmegaConf.to_container(cfg.demos.policy, resolve=True)})
        stats, stopped = rec.stats(), rec.stopped_early
    size = dataset_bytes(path) if path is not None else 0
    summary = RecordSummary(path, stats["recorded"], stats["kept"], time.perf_counter() - start,
                            size, stopped)
    print(f"recorded {_figures(summary.recorded)}")
    print(f"kept ({cfg.keep}) {_figures(summary.kept)}")
    where = f"{path} ({size / 1e6:.1f} MB)" if path is not None else "nothing saved (no episode kept)"
    print(f"dataset: {where}; {summary.seconds:.1f} s")
    return summary


@hydra.main(version_base="1.3", config_path="../conf", config_name="record")
def main(cfg: DictConfig) -> None:
    run_task(record, cfg)


if __name__ == "__main__":
    register_configs()
    run_hydra(main)
