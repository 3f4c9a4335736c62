"""``python -m memrl.record``: record prior-knowledge datasets (scripted driver or a person)."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import hydra
from omegaconf import DictConfig, OmegaConf

from memrl.cli import run_hydra, run_task
from memrl.configs import register_configs
from memrl.errors import UserError, instantiate_checked
from memrl.schemas import check_record
from memrl.stop import EXIT_OF, SignalGuard, Stopped, how_stopped

if TYPE_CHECKING:
    from memrl.data.recording import Recording

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


def resume_command(folder: Path | str, source: str = "scripted") -> str:
    """The command that goes on with a stopped recording (``demos=`` when not the default)."""
    demos = "" if source == "scripted" else f"demos={source} "
    return f"python -m memrl.record {demos}resume={folder}"


def record(cfg: DictConfig) -> RecordSummary:
    """Record ``cfg.episodes`` episodes of ``cfg.demos.policy`` into a dataset and report.

    With ``cfg.example``, make or check the cached scripted example for ``cfg.env`` instead.
    With ``cfg.resume``, go on with the stopped recording in that folder (its plan).

    Raises:
        Stopped: Esc, Ctrl-C or SIGTERM ended it early (exit 130/143); its line says what was
            saved and the command that goes on with it.
    """
    check_record(cfg)  # every value, and the output folder writable, before recording
    start = time.perf_counter()
    if cfg.example:
        return _example(cfg, start)
    from memrl.data.demos import dataset_bytes

    with SignalGuard() as guard:
        path, rec, out, planned = _record(cfg, guard)
    stats = rec.stats()
    size = dataset_bytes(path) if path is not None else 0
    summary = RecordSummary(path, stats["recorded"], stats["kept"], time.perf_counter() - start,
                            size, rec.stopped_early)
    if rec.stopped_early:
        raise Stopped.by(_stopped_line(rec, summary, out, planned, str(cfg.demos.source)), rec.interrupted)
    _print(summary, cfg.keep)
    if guard.pending is not None:  # a signal during the save: the dataset is whole; stop now
        raise Stopped(f"interrupted during the save; the dataset is complete: {path}",
                      EXIT_OF[guard.pending])  # type: ignore[index]
    return summary


def _record(cfg: DictConfig, guard: SignalGuard) -> tuple[Path | None, Recording, Path, int]:
    from memrl.data.recording import record_to_dataset
    from memrl.data.sittings import read_plan

    person = cfg.demos.get("person")
    kw: dict[str, Any] = {
        "episodes": int(cfg.episodes), "seed": int(cfg.seed), "keep_stable": cfg.keep == "stable",
        "tail_steps": cfg.tail_steps, "action_noise": float(cfg.action_noise),
        "source": str(cfg.demos.source)}
    env: Any = cfg.env
    out, resume = Path(str(cfg.out)), None
    if cfg.get("resume") is not None:
        out = Path(str(cfg.resume))
        resume = read_plan(out)
        plan = resume[0]
        if plan.source != kw["source"]:
            raise UserError(f"resume: {out} was recorded with demos={plan.source}, not "
                            f"demos={kw['source']}; add demos={plan.source}")
        kw.update(episodes=plan.episodes, seed=plan.seed, keep_stable=plan.keep == "stable",
                  tail_steps=plan.tail_steps, action_noise=plan.action_noise)
        env, person = plan.env_config, person or plan.person
        log.info("resuming %s: episode %d of %d", out, plan.next_episode + 1, plan.episodes)
    policy = instantiate_checked(cfg.demos.policy)
    path, rec = record_to_dataset(
        env, policy, out, render=bool(getattr(policy, "needs_render", False)),
        progress=bool(cfg.progress), overwrite=bool(cfg.overwrite), person=person, resume=resume,
        guard=guard, extra={"policy": OmegaConf.to_container(cfg.demos.policy, resolve=True)}, **kw)
    return path, rec, out, int(kw["episodes"])


def _stopped_line(rec: Recording, summary: RecordSummary, out: Path, planned: int, source: str) -> str:
    what = how_stopped(rec.interrupted)
    if not rec.episodes:
        return f"{what} before any episode finished; nothing saved"
    kept = summary.kept
    saved = (f"{kept['episodes']} episodes kept ({kept['transitions']} transitions) saved in {out}"
             if summary.path is not None else f"no episode kept yet; the plan is saved in {out}")
    return (f"{what} after episode {rec.next_episode} of {planned}: {saved}; "
            f"go on with: {resume_command(out, source)}")


def _print(summary: RecordSummary, keep: str) -> None:
    print(f"recorded {_figures(summary.recorded)}")
    k = summary.kept
    print(f"kept ({keep}) {k['episodes']} episodes, {k['transitions']} transitions saved (of their "
          f"{k['steps']} steps): survival {k['survival']}/{k['episodes']}, goal {k['goal']}/"
          f"{k['episodes']}, mean return {k['mean_return']:.1f}")
    where = (f"{summary.path} ({summary.bytes / 1e6:.1f} MB)" if summary.path is not None
             else "nothing saved (no episode kept)")
    print(f"dataset: {where}; {summary.seconds:.1f} s")


def _example(cfg: DictConfig, start: float) -> RecordSummary:
    from memrl.data.demos import dataset_bytes, read_metadata
    from memrl.data.recording import ensure_example_demos

    started = datetime.now(UTC).replace(microsecond=0)
    path = ensure_example_demos(cfg.env, cfg.paths.data_dir, cfg.recipe, overwrite=bool(cfg.overwrite),
                                progress=bool(cfg.progress))
    meta = read_metadata(path)
    stats = meta["stats"]
    made = datetime.fromisoformat(meta["created"])
    print(f"example dataset {'recorded now' if made >= started else 'from the cache'}: {path}")
    summary = RecordSummary(path, stats["recorded"], stats["kept"], time.perf_counter() - start,
                            dataset_bytes(path))
    print(f"recorded {_figures(summary.recorded)}")
    print(f"kept ({cfg.keep}) {_figures(summary.kept)}")
    print(f"dataset: {path} ({summary.bytes / 1e6:.1f} MB); {summary.seconds:.1f} s")
    return summary


@hydra.main(version_base="1.3", config_path="conf", config_name="record")
def main(cfg: DictConfig) -> None:
    run_task(record, cfg)


if __name__ == "__main__":
    register_configs()
    run_hydra(main)
