"""Mode B stage 1 side by side: eq. (1) alone vs with the large-margin loss on the demos, or
any other variants given as train overrides.

Trains stage 1 on the cached scripted example demos for each variant (or on demos the variant
records itself, see :func:`record_variant_demos`), then drives the greedy agent through 20
non-goal episodes with 0-5 cars; reports action agreement on the held-out demos after every
``check_every`` updates, updates/s, survival, goal, and both in the same episode.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from tempfile import TemporaryDirectory
from typing import Any

from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf

import memrl

CONF_DIR = str(memrl.CONF_DIR)


def drive_greedy(qnet: Any, env_cfg: dict[str, Any], episodes: int) -> tuple[int, int, int]:
    """(survived, reached, both in the same episode) of the greedy agent over ``episodes``
    non-goal episodes with 0-5 cars, reset with seeds 10,000, 10,001, ..."""
    from memrl.dqn.stage1 import drive_counts

    counts = drive_counts(qnet, env_cfg, [10_000 + i for i in range(episodes)])
    return counts["survived"], counts["reached"], counts["both"]


class _DriveCurve:
    """Drives the greedy agent every ``every`` updates of a stage-1 run, before the last."""

    def __init__(self, trainer: Any, env_cfg: dict[str, Any], episodes: int, every: int,
                 last: int) -> None:
        self.trainer, self.env_cfg, self.episodes = trainer, env_cfg, episodes
        self.every, self.last = every, last
        self.points: list[dict[str, int]] = []
        self.seconds = 0.0
        """Time spent driving [s]."""

    def __call__(self, done: int) -> None:
        if self.every > 0 and done % self.every == 0 and done < self.last:
            start = time.perf_counter()
            s, r, b = drive_greedy(self.trainer.learner.qnet, self.env_cfg, self.episodes)
            self.points.append({"updates": done, "survived": s, "reached": r, "both": b})
            self.seconds += time.perf_counter() - start


def record_variant_demos(env_cfg: dict[str, Any], recipe: dict[str, Any], folder: Path) -> Path:
    """Record a variant's own scripted demos: ``recipe`` holds the keys of
    :class:`memrl.data.recipe.DemoRecipe` that differ from the default recipe."""
    from memrl.data.recording import record_recipe

    path, rec = record_recipe(env_cfg, recipe, folder)
    if path is None:
        raise RuntimeError(f"the scripted driver kept no episode: {rec.stats()['recorded']}")
    return path


DEFAULT_VARIANTS: list[dict[str, Any]] = [
    {"name": "td_only", "overrides": ["mode.stage1.margin_weight=0"]},
    {"name": "margin", "overrides": []},
]
"""Stage-1 variants compared by default: eq. (1) alone, and with the large-margin loss."""


def run(updates: int = 800, variants: list[dict[str, Any]] | None = None, check_every: int = 100,
        episodes: int = 20, data_dir: str | None = None, threads: int = 1,
        drive_every: int = 0) -> dict[str, Any]:
    """One stage-1 training per variant (train overrides, e.g. ``env.bev.path_length=20``),
    same seed; each trains on the cached scripted example demos of its own env config, or,
    when the variant has a ``demos`` recipe, on demos recorded for it. ``drive_every`` > 0
    also drives the greedy agent every that many updates (a ``curve`` per run; its driving
    time is left out of updates/s)."""
    from memrl.configs import register_configs
    from memrl.data.demos import load_demos
    from memrl.data.recording import ensure_example_demos
    from memrl.dqn.loop import Trainer

    register_configs()
    out: dict[str, Any] = {"updates": updates, "episodes": episodes, "runs": []}
    for variant in variants or DEFAULT_VARIANTS:
        name, overrides = str(variant["name"]), list(variant.get("overrides") or [])
        GlobalHydra.instance().clear()
        with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
            cfg = compose("train", ["+mode=B", "progress=false", "logger=none",
                                    f"agent.threads={threads}", f"mode.stage1.max_updates={updates}",
                                    f"mode.stage1.check_every={check_every}",
                                    "mode.stage1.criterion=max_updates", *overrides])
        env_cfg: dict[str, Any] = OmegaConf.to_container(cfg.env, resolve=True)  # type: ignore[assignment]
        data = Path(data_dir) if data_dir else Path(os.environ.get("MEMRL_ROOT", ".")) / "outputs" / "data"
        with TemporaryDirectory() as tmp:
            recipe = variant.get("demos")
            source = record_variant_demos(env_cfg, dict(recipe), Path(tmp) / "demos") \
                if recipe else ensure_example_demos(env_cfg, data, cfg.mode.example)
            demos = load_demos(source, env_cfg=env_cfg).to_tensordict()
            trainer = Trainer(cfg, Path(tmp) / "run", demos)
            curve = _DriveCurve(trainer, env_cfg, episodes, drive_every, updates)
            start = time.perf_counter()
            trainer.run_offline(curve)
            wall = time.perf_counter() - start - curve.seconds - trainer.offline_progress.drive_s
            survived, reached, both = drive_greedy(trainer.learner.qnet, env_cfg, episodes)
            curve.points.append({"updates": updates, "survived": survived, "reached": reached,
                                 "both": both})
        out["runs"].append({"variant": name, "overrides": list(overrides),
                            "margin_weight": float(cfg.mode.stage1.margin_weight),
                            "demos": len(demos), "demo_recipe": recipe or "example",
                            "agreements": [round(a, 3) for a in trainer.offline_progress.agreements],
                            "last_check_parts": {k: round(v, 3) for k, v in
                                                 trainer.offline_progress.parts[-1].items()},
                            "stop": trainer.offline_progress.stop_reason,
                            "drives": trainer.offline_progress.drives,
                            "best_updates": trainer.offline_progress.best_updates,
                            "drive_s": round(trainer.offline_progress.drive_s, 1),
                            "updates_per_s": round(updates / wall, 2), "wall_s": round(wall, 1),
                            "survived_non_goal": survived, "reached_non_goal": reached,
                            "both_non_goal": both, "curve": curve.points})
    return out
