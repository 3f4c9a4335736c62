"""Mode B stage 1 side by side: eq. (1) alone vs with the large-margin loss on the demos, or
any other variants given as train overrides.

Trains stage 1 on the cached scripted example demos for each variant, then drives the
greedy agent through 20 non-goal episodes with 0-5 cars; reports action agreement on the
held-out demos after every ``check_every`` updates, updates/s, survival and goal counts.
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

CONF_DIR = str(Path(__file__).resolve().parents[2] / "conf")


def _drive(qnet: Any, env_cfg: dict[str, Any], episodes: int) -> tuple[int, int]:
    from memrl.checkpoint import GreedyQPolicy
    from memrl.envs.torchrl_env import make_env, unwrap
    from memrl.modules.policy import PolicyModule

    env = make_env({**env_cfg, "vehicles_count": [0, 5], "initial_lane": "non_goal"}, seed=0)
    module = PolicyModule(GreedyQPolicy(qnet), unwrap(env))
    survived = reached = 0
    for episode in range(episodes):
        td = env.reset(seed=10_000 + episode)
        out = env.rollout(int(env_cfg.get("duration", 300)), module, tensordict=td,
                          auto_reset=False, break_when_any_done=True)
        survived += int(not out["next", "collided"].any())
        reached += int(out["next", "reached_target"].any())
    return survived, reached


DEFAULT_VARIANTS: list[dict[str, Any]] = [
    {"name": "td_only", "overrides": ["mode.stage1.margin_weight=0"]},
    {"name": "margin", "overrides": []},
]
"""Stage-1 variants compared by default: eq. (1) alone, and with the large-margin loss."""


def run(updates: int = 800, variants: list[dict[str, Any]] | None = None, check_every: int = 100,
        episodes: int = 20, data_dir: str | None = None, threads: int = 1) -> dict[str, Any]:
    """One stage-1 training per variant (train overrides, e.g. ``env.bev.path_length=20``),
    same seed; each trains on the cached scripted example demos of its own env config."""
    from memrl.configs import register_configs
    from memrl.data.demos import ensure_example_demos, load_demos
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
        demos = load_demos(ensure_example_demos(env_cfg, data), env_cfg=env_cfg)
        with TemporaryDirectory() as tmp:
            trainer = Trainer(cfg, Path(tmp), demos)
            trainer._t_start, trainer._frames0, trainer._updates0 = time.perf_counter(), 0, 0
            start = time.perf_counter()
            trainer.run_stage1()
            wall = time.perf_counter() - start
            survived, reached = _drive(trainer.learner.qnet, env_cfg, episodes)
        out["runs"].append({"variant": name, "overrides": list(overrides),
                            "margin_weight": float(cfg.mode.stage1.margin_weight),
                            "demos": len(demos),
                            "agreements": [round(a, 3) for a in trainer.stage1.agreements],
                            "last_check_parts": {k: round(v, 3) for k, v in
                                                 trainer.stage1.parts[-1].items()},
                            "updates_per_s": round(updates / wall, 2), "wall_s": round(wall, 1),
                            "survived_non_goal": survived, "reached_non_goal": reached})
    return out
