"""Slow learning check (``pytest -m slow``): mode B's stage 1 on scripted prior knowledge."""

from __future__ import annotations

import json
import time

import pytest
from omegaconf import OmegaConf

from memrl.checkpoint import GreedyQPolicy
from memrl.data.demos import load_demos
from memrl.data.recording import record_to_dataset
from memrl.dqn.loop import Trainer
from memrl.envs.torchrl_env import make_env, unwrap
from memrl.modules.policy import PolicyModule
from memrl.modules.scripted import ScriptedDriver


@pytest.mark.slow
def test_stage1_agent_drives_like_the_demonstrations(compose_cfg, tmp_path):
    cfg = compose_cfg("train", [
        "+mode=B", "+experiment=imitation", "progress=false", "logger=none",
        f"paths.data_dir={tmp_path / 'data'}",
    ])
    env_cfg = OmegaConf.to_container(cfg.env, resolve=True)
    # Manoeuvre-focused prior knowledge (README): 240 non-goal starts among 0-5 cars, each
    # kept up to 30 steps after the target lane is reached, from the position-rule driver,
    # recorded with 20% random actions of which only the driver's recoveries are stored.
    record_cfg = {**env_cfg, "initial_lane": "non_goal", "vehicles_count": [0, 5]}
    driver = ScriptedDriver(merge_window=12.0, speed_tolerance=0.3)
    start = time.perf_counter()
    path, _ = record_to_dataset(record_cfg, driver, tmp_path / "demos", episodes=240, seed=0,
                                keep_stable=True, tail_steps=30, action_noise=0.2,
                                source="scripted")
    record_s = time.perf_counter() - start
    demos = load_demos(path, env_cfg=cfg.env)
    trainer = Trainer(cfg, tmp_path / "run", demos)
    trainer._t_start, trainer._frames0, trainer._updates0 = time.perf_counter(), 0, 0
    start = time.perf_counter()
    trainer.run_stage1()
    wall = time.perf_counter() - start
    policy = GreedyQPolicy(trainer.learner.qnet)
    env = make_env({**env_cfg, "vehicles_count": [0, 5], "initial_lane": "non_goal"}, seed=0)
    module = PolicyModule(policy, unwrap(env))
    survived = reached = both = 0
    for episode in range(20):
        td = env.reset(seed=10_000 + episode)
        out = env.rollout(300, module, tensordict=td, auto_reset=False, break_when_any_done=True)
        ok, goal = not bool(out["next", "collided"].any()), bool(out["next", "reached_target"].any())
        survived, reached, both = survived + ok, reached + goal, both + (ok and goal)
    report = {"demos": len(demos), "record_s": round(record_s, 1),
              "stage1_updates": trainer.stage1.updates, "stop": trainer.stage1.stop_reason,
              "agreements": [round(a, 3) for a in trainer.stage1.agreements],
              "last_check_parts": trainer.stage1.parts[-1],
              "wall_s": round(wall, 1), "updates_per_s": round(trainer.stage1.updates / wall, 2),
              "survived_of_20": survived, "reached_of_20": reached, "both_of_20": both}
    print(json.dumps(report))
    (tmp_path / "report.json").write_text(json.dumps(report))
    # "survives and reaches the target in most of 20 episodes": both in the same episode
    assert both >= 11, report
