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
        "+mode=B", "progress=false", "logger=none", f"paths.data_dir={tmp_path / 'data'}",
        "mode.stage1.max_updates=2000", "mode.stage1.check_every=250",
        "mode.stage1.criterion=max_updates",
    ])
    # 20 scripted episodes from non-goal starts: every one holds a lane change.
    env_cfg = {**OmegaConf.to_container(cfg.env, resolve=True), "initial_lane": "non_goal"}
    path, _ = record_to_dataset(env_cfg, ScriptedDriver(), tmp_path / "demos", episodes=20,
                                seed=0, keep_stable=True, source="scripted")
    demos = load_demos(path, env_cfg=cfg.env)
    trainer = Trainer(cfg, tmp_path / "run", demos)
    trainer._t_start, trainer._frames0, trainer._updates0 = time.perf_counter(), 0, 0
    start = time.perf_counter()
    trainer.run_stage1()
    wall = time.perf_counter() - start
    policy = GreedyQPolicy(trainer.learner.qnet)
    env = make_env({**OmegaConf.to_container(cfg.env, resolve=True), "vehicles_count": [0, 5],
                    "initial_lane": "non_goal"}, seed=0)
    module = PolicyModule(policy, unwrap(env))
    survived = reached = 0
    for episode in range(20):
        td = env.reset(seed=10_000 + episode)
        out = env.rollout(300, module, tensordict=td, auto_reset=False, break_when_any_done=True)
        survived += int(not out["next", "collided"].any())
        reached += int(out["next", "reached_target"].any())
    report = {"demos": len(demos), "stage1_updates": trainer.stage1.updates,
              "stop": trainer.stage1.stop_reason, "agreements": trainer.stage1.agreements,
              "last_check_parts": trainer.stage1.parts[-1],
              "wall_s": round(wall, 1), "updates_per_s": round(trainer.stage1.updates / wall, 2),
              "survived_of_20": survived, "reached_of_20": reached}
    print(json.dumps(report))
    (tmp_path / "report.json").write_text(json.dumps(report))
    assert survived >= 11 and reached >= 11, report
