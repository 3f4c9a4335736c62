"""DAgger with the scripted driver on call: labels, aggregation, the run folder, evaluation."""

from __future__ import annotations

import csv
import json
import re

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from memrl.dagger import dagger
from memrl.dqn.collector import episode_seed
from memrl.envs.batched import BatchedLaneChange
from memrl.envs.lane_change import LaneChangeEnv
from memrl.errors import UserError
from memrl.evaluate import evaluate
from memrl.imitation.dagger import Driver
from memrl.imitation.expert import ExpertLabeler
from memrl.modules.scripted import ScriptedDriver

CONFIG = {"initial_lane": "non_goal", "vehicles_count": [2, 5], "duration": 25}
SMALL_EVAL = ["protocol.episodes=2", "protocol.duration=20", "workers=1", "batch=2", "progress=false"]


def test_labels_are_the_scripted_drivers_actions_on_states_the_expert_never_chose():
    """Drive reference envs and the engine with mostly random actions; at every state the
    labeler's action is that of a scripted driver reading the reference env."""
    seeds = [3, 4, 5]
    refs = [LaneChangeEnv(config=CONFIG) for _ in seeds]
    drivers = [ScriptedDriver() for _ in seeds]
    for env, driver, seed in zip(refs, drivers, seeds, strict=True):
        env.reset(seed=seed)
        driver.reset(env)
    engine = BatchedLaneChange(CONFIG, len(seeds))
    engine.reset(seeds=seeds)
    labeler = ExpertLabeler(engine, ScriptedDriver)
    rng = np.random.default_rng(0)
    compared = off_expert = resets = 0
    for _ in range(60):
        labels = labeler.labels()
        expected = [d.act(env, None) for d, env in zip(drivers, refs, strict=True)]
        assert labels.tolist() == expected
        compared += len(seeds)
        actions = np.where(rng.random(len(seeds)) < 0.7, rng.integers(9, size=len(seeds)), labels)
        off_expert += int((actions != labels).sum())
        engine.step(torch.as_tensor(actions))
        done = []
        for i, env in enumerate(refs):
            _, _, terminated, truncated, _ = env.step(int(actions[i]))
            if terminated or truncated:
                env.reset()
                drivers[i].reset(env)
                done.append(i)
        if done:
            engine.reset(done)
            labeler.new_episodes(done)
            resets += len(done)
    assert compared == 180 and off_expert > 60 and resets >= 3


def _cfg(compose_cfg, tmp_path, *overrides):
    cfg = compose_cfg("dagger", ["iterations=3", "steps_per_iteration=4", "env.num_envs=2", "epochs=1",
                                 "batch_size=4", "agent.threads=1", "env.duration=20", *overrides])
    cfg.paths.output_dir = str(tmp_path / "run")
    return cfg


def test_iteration_zero_drives_the_expert_in_the_training_scenes(compose_cfg, tmp_path):
    cfg = _cfg(compose_cfg, tmp_path)
    drive = Driver(cfg)
    obs, labels, chosen, _ = drive.collect(4, None, 0.0)
    assert obs.shape == (8, 4, 84, 84) and labels.tolist() == chosen.tolist()
    # the same scenes (the trainer's episode seeds) driven by the scripted driver in reference envs
    env_values = OmegaConf.to_container(cfg.env, resolve=True)
    for i in range(2):
        env = LaneChangeEnv(config=env_values)
        env.reset(seed=episode_seed(0, i))
        driver = ScriptedDriver()
        driver.reset(env)
        for step in range(4):
            action = driver.act(env, None)
            assert labels[2 * step + i] == action
            env.step(action)


def test_dagger_aggregates_labels_over_iterations_and_its_run_evaluates(compose_cfg, tmp_path):
    cfg = _cfg(compose_cfg, tmp_path)
    run = dagger(cfg)
    with (run / "dagger.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [(int(r["iteration"]), int(r["collected"]), int(r["dataset"])) for r in rows] == \
        [(0, 8, 8), (1, 8, 16), (2, 8, 24)]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["dataset"] == 24 and summary["env_steps"] == 24 and summary["loss"] == "cross_entropy"
    assert (run / "checkpoints" / "final.pt").is_file() and (run / "config.yaml").is_file()
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == \
        ["final.pt", "iteration_0.pt", "iteration_1.pt", "iteration_2.pt"]
    [result] = evaluate(compose_cfg("evaluate", [f"policy.run={run}", *SMALL_EVAL]), out_dir=tmp_path / "x")
    assert result.name == "DAgger" and result.path == run / "eval"
    doc = json.loads((run / "eval" / "eval.json").read_text())
    assert sorted(doc["scores"]) == ["non_goal", "random"] and doc["crashes"]["non_goal"]["episodes"] == 2


@pytest.mark.parametrize(("override", "message"), [
    ("iterations=0", "'iterations': must be >= 1"),
    ("beta=1.5", "'beta': must be in [0.0, 1.0], got 1.5"),
    ("env.vehicles_count=[5,0]", "vehicles_count"),
])
def test_bad_dagger_values_are_refused_naming_the_key(compose_cfg, tmp_path, override, message):
    from memrl.schemas import check_dagger

    with pytest.raises(UserError, match=re.escape(message)):
        check_dagger(_cfg(compose_cfg, tmp_path, override))
