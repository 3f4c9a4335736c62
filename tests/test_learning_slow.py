"""Slow learning check (``pytest -m slow``): mode B's stage 1 on scripted prior knowledge."""

from __future__ import annotations

import json
import time

import pytest
from omegaconf import OmegaConf

from memrl.benchmarks.stage1_check import drive_greedy, record_variant_demos
from memrl.data.demos import load_demos
from memrl.dqn.loop import Trainer


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2, 3], ids=lambda s: f"seed{s}")
def test_stage1_agent_drives_like_the_demonstrations(compose_cfg, tmp_path, seed):
    """One seed of the check (``-k seed0``: the test's own); the four of them show whether
    the recipe holds beyond the seed it was tuned on. Up to ~35 min each on 2 cores."""
    cfg = compose_cfg("train", [
        "+mode=B", "+experiment=imitation", "progress=false", "logger=none",
        f"paths.data_dir={tmp_path / 'data'}", f"seed={seed}",
    ])
    env_cfg = OmegaConf.to_container(cfg.env, resolve=True)
    # The default prior knowledge (mode.example, memrl/data/recipe.py; README): 240 non-goal
    # starts among 0-5 cars, each kept up to 30 steps after the target lane is reached, from
    # the position-rule driver, recorded with 20% random actions of which only the driver's
    # recoveries are stored. Stage 1 drives 40 episodes of its own scenes every 1,000 updates,
    # stops at 75% of them or 20,000 updates and keeps the weights that drove best; the 20
    # episodes below are other scenes (seeds 10,000+).
    recipe = {"seed": 5000 * seed}  # its own demo episodes
    start = time.perf_counter()
    path = record_variant_demos(env_cfg, recipe, tmp_path / "demos")
    record_s = time.perf_counter() - start
    demos = load_demos(path, env_cfg=cfg.env)
    trainer = Trainer(cfg, tmp_path / "run", demos)
    trainer._t_start, trainer._frames0, trainer._updates0 = time.perf_counter(), 0, 0
    start = time.perf_counter()
    trainer.run_offline()
    wall = time.perf_counter() - start
    p = trainer.offline_progress
    survived, reached, both = drive_greedy(trainer.learner.qnet, env_cfg, 20)
    report = {"seed": seed, "demo_seed": 5000 * seed, "demos": len(demos), "record_s": round(record_s, 1),
              "stage1_updates": p.updates, "stop": p.stop_reason,
              "agreements": [round(a, 3) for a in p.agreements],
              "last_check_parts": p.parts[-1],
              "drives": p.drives, "best_updates": p.best_updates,
              "wall_s": round(wall, 1), "drive_s": round(p.drive_s, 1),
              "updates_per_s": round(p.updates / (wall - p.drive_s), 2),
              "survived_of_20": survived, "reached_of_20": reached, "both_of_20": both}
    print(json.dumps(report))
    (tmp_path / "report.json").write_text(json.dumps(report))
    # "survives and reaches the target in most of 20 episodes": both in the same episode
    assert both >= 11, report


STAGE2_FRAMES = 20_000
"""Stage-2 env steps of the mode B check (4,876 updates at the default replay ratio)."""
REACHED_BAR = 10
"""Test episodes of 20 in which the final agent must reach the target lane (the random policy:
3 of 100). On today's defaults (stage 2 keeps the demos at 10% with the margin loss) the runs
of the study margin20k (docs/results/issue20, section 5; stage 2 from the study cand20k's
stage-1 weights, seeds 0-2; this check is seed 0) reached it in 17, 18 and 14 of these 20
episodes; the paper's stage 2 from the same weights in 7, 7 and 7. 10 leaves room for another
CPU's arithmetic and a stage 1 of its own. This check itself, run 2026-11-24 (AMD EPYC, 2 cores,
beside other jobs): reached 15, survived 14, both 12 of 20, 21,876 updates, 2,957 s."""


@pytest.mark.slow
def test_mode_b_changes_lanes_after_stage_2(compose_cfg, tmp_path):
    """Mode B end to end on the default prior knowledge with ``+experiment=imitation``:
    stage 1 until its drives say it changes lanes, then STAGE2_FRAMES env steps of stage 2 on
    16 envs; the final greedy agent drives 20 non-goal test episodes among 0-5 cars (scenes
    10,000+, never trained on) and changes into the target lane in at least REACHED_BAR."""
    from memrl.checkpoint import load_qnet
    from memrl.train import train

    cfg = compose_cfg("train", [
        "+mode=B", "+experiment=imitation", "progress=false", "logger=none", "seed=0",
        f"paths.data_dir={tmp_path / 'data'}", f"total_frames={STAGE2_FRAMES}",
        "total_episodes=null", "env.num_envs=16", "eval.every=0",
    ])
    start = time.perf_counter()
    summary = train(cfg, tmp_path / "run")
    qnet, _ = load_qnet(tmp_path / "run" / "checkpoints" / "final.pt")
    env_cfg = OmegaConf.to_container(cfg.env, resolve=True)
    survived, reached, both = drive_greedy(qnet, env_cfg, 20)
    report = {"frames": summary.frames, "updates": summary.updates,
              "wall_s": round(time.perf_counter() - start, 1), "survived_of_20": survived,
              "reached_of_20": reached, "both_of_20": both}
    print(json.dumps(report))
    assert reached >= REACHED_BAR, report
