"""Training runs of every mode, mode B's stage switch, and resume equivalence."""

from __future__ import annotations

import json
import logging
import re

import pytest
import torch
from hydra.errors import HydraException

from memrl.checkpoint import resume as ckpt
from memrl.dqn.loop import Trainer
from memrl.errors import UserError, one_line
from memrl.train import train
from tests.helpers import TINY, assert_same_final_weights_and_agent_buffers, csv_rows, tiny

rows = csv_rows


@pytest.mark.parametrize("mode", [None, "A", "B"])
def test_smoke_run_of_each_mode_writes_its_outputs(compose_cfg, tmp_path, demos, mode):
    overrides = tiny(mode)
    cfg = compose_cfg("train", overrides)
    summary = train(cfg, tmp_path, demos=demos if mode else None)
    assert summary.episodes == 3 and summary.updates > 0
    for name in ("config.yaml", "episodes.csv", "updates.csv", "summary.json",
                 "checkpoints/last/state.pt", "checkpoints/final.pt"):
        assert (tmp_path / name).exists(), name
    episodes = rows(tmp_path / "episodes.csv")
    assert [int(r["episode"]) for r in episodes] == [1, 2, 3]
    assert set(episodes[0]) >= {"return", "survival_steps", "collided", "reached_target",
                                "epsilon", "stage"}
    updates = rows(tmp_path / "updates.csv")
    assert updates and all(float(r["loss"]) >= 0 for r in updates)
    if mode == "A":  # exactly round(0.1 * 8) = 1 demo in every batch
        assert {(r["demo_count_min"], r["demo_count_max"]) for r in updates} == {("1", "1")}
    if mode == "B":
        assert summary.stage == "B2" and summary.stage1["done"]
        assert {r["stage"] for r in updates} == {"B1", "B2"}
        assert (tmp_path / "checkpoints" / "stage1.pt").exists()
    assert json.loads((tmp_path / "summary.json").read_text())["episodes"] == 3


def test_mode_b_switches_when_its_criterion_fires_and_stage2_starts_from_stage1(
        compose_cfg, tmp_path, demos):
    cfg = compose_cfg("train", tiny("B") + ["mode.stage1.criterion=agreement",
                                       "mode.stage1.agreement=0.0", "mode.stage1.max_updates=100",
                                       "mode.stage1.lr=0.003"])
    trainer = Trainer(cfg, tmp_path, demos)
    trainer._t_start, trainer._frames0, trainer._updates0 = 0.0, 0, 0
    assert {g["lr"] for g in trainer.learner.optimizer.param_groups} == {0.003}
    trainer.run_offline()
    # stage 2 gets a fresh Adam at agent.lr
    assert {g["lr"] for g in trainer.learner.optimizer.param_groups} == {cfg.agent.lr}
    assert not trainer.learner.optimizer.state
    # agreement >= 0 holds at the first check: stage 1 stops after check_every updates
    p = trainer.offline_progress
    assert p.updates == 4 and p.stop_reason.startswith("agreement")
    # a fresh buffer: no agent data yet, the prior knowledge at round(0.1 x 400) = 40 items
    buffer = trainer.stage.buffer
    assert trainer.counters.stage == "B2" and len(buffer.online_buffer) == 0
    assert len(buffer.offline_buffer) == len(buffer) == 40
    saved = torch.load(tmp_path / "checkpoints" / "stage1.pt", weights_only=False)["loss_module"]
    now = trainer.learner.loss_module.state_dict()
    online = [k for k in saved if k.startswith("value_network_params")]
    assert online and all(torch.equal(saved[k], now[k]) for k in online)
    for k in online:  # the target network starts from the stage-1 online weights too
        assert torch.equal(now["target_" + k], saved[k])
    assert float(trainer.stage.explore.eps) == pytest.approx(cfg.mode.stage2.eps_start)


def test_mode_b_stage2_has_its_own_rate_and_n_step_when_set(compose_cfg, tmp_path, demos):
    """mode.stage2.lr / n_step: stage 2's fresh Adam runs at its own rate and its buffer (demo
    and agent parts) sums its own steps; stage 1 keeps its own rate and agent.n_step (1)."""
    from memrl.data.nstep import STEPS_KEY

    cfg = compose_cfg("train", tiny("B") + ["mode.stage1.criterion=max_updates",
                                       "mode.stage1.max_updates=4", "mode.stage1.lr=0.003",
                                       "mode.stage2.lr=0.0007", "mode.stage2.n_step=3"])
    trainer = Trainer(cfg, tmp_path, demos)
    trainer._t_start, trainer._frames0, trainer._updates0 = 0.0, 0, 0
    assert {g["lr"] for g in trainer.learner.optimizer.param_groups} == {0.003}
    assert STEPS_KEY not in trainer.stage.buffer.sample().keys()  # stage 1: 1-step
    trainer.run_offline()
    assert trainer.counters.stage == "B2"
    assert {g["lr"] for g in trainer.learner.optimizer.param_groups} == {0.0007}
    assert not trainer.learner.optimizer.state
    buffer = trainer.stage.buffer
    assert buffer.offline_buffer.storage.n_step == buffer.online_buffer.storage.n_step == 3
    assert STEPS_KEY in buffer.offline_buffer.sample(4).keys()
    for bad, line in ((["mode.stage2.lr=0"], "config 'mode.stage2.lr': must be > 0 or null, got 0"),
                      (["mode.stage2.n_step=0"], "config 'mode.stage2.n_step': must be >= 1 or null, got 0")):
        with pytest.raises(UserError, match=re.escape(line)):
            train(compose_cfg("train", tiny("B") + bad), tmp_path / "bad")


def test_updates_per_round_sets_the_replay_ratio_and_stage2_can_have_its_own(compose_cfg, tmp_path, demos):
    """agent.updates_per_round: that many updates per due round in every online stage;
    mode.stage2.updates_per_round: stage 2's own (stage 1's update count is its stop rule's)."""
    from memrl.dqn.schedule import UpdateSchedule

    rounds = UpdateSchedule(4, 20).rounds_due  # TINY's train_every and warmup_frames
    two = train(compose_cfg("train", tiny() + ["agent.updates_per_round=2"]), tmp_path / "d2", demos=demos)
    assert two.frames > 20 and two.updates == 2 * rounds(two.frames)
    b = tiny("B") + ["mode.stage1.criterion=max_updates"]
    own = train(compose_cfg("train", b + ["mode.stage2.updates_per_round=3"]), tmp_path / "b3", demos=demos)
    assert own.stage1["updates"] == 12  # the stop rule's, not 3x
    assert own.updates == own.stage1["updates"] + 3 * rounds(own.frames)
    both = train(compose_cfg("train", b + ["agent.updates_per_round=2"]), tmp_path / "b2", demos=demos)
    assert both.updates == both.stage1["updates"] + 2 * rounds(both.frames)  # null: agent's
    with pytest.raises(UserError, match=re.escape(
            "config 'mode.stage2.updates_per_round': must be >= 1 or null, got 0")):
        train(compose_cfg("train", b + ["mode.stage2.updates_per_round=0"]), tmp_path / "bad", demos=demos)


def test_stage1_stops_at_max_updates_without_a_criterion(compose_cfg, tmp_path, demos):
    cfg = compose_cfg("train", tiny("B") + ["mode.stage1.criterion=max_updates",
                                       "mode.stage1.max_updates=6"])
    trainer = Trainer(cfg, tmp_path, demos)
    trainer._t_start, trainer._frames0, trainer._updates0 = 0.0, 0, 0
    trainer.run_offline()
    assert trainer.offline_progress.updates == 6 and "max_updates" in trainer.offline_progress.stop_reason
    s1 = trainer.offline_progress
    assert len(s1.parts) == len(s1.agreements) == 2  # checks at 4 and at the stop (6)
    assert all(0 <= v <= 1 for part in s1.parts for v in part.values())


def test_stage2_from_another_runs_stage1_trains_no_stage1_of_its_own(compose_cfg, tmp_path, demos,
                                                                    caplog):
    """mode.stage1.init: stage 2 starts from the named run's stage-1 weights (online and
    target), with a fresh Adam, and runs the same stage-2 schedule as that run did."""
    b = tiny("B") + ["mode.stage1.criterion=max_updates"]
    source = train(compose_cfg("train", b), tmp_path / "src", demos=demos)
    src_updates = source.stage1["updates"]
    assert src_updates == 12
    cfg = compose_cfg("train", b + [f"mode.stage1.init={tmp_path / 'src'}",
                                       "agent.exploration=ez_greedy"])
    trainer = Trainer(cfg, tmp_path / "run", demos)
    trainer._t_start, trainer._frames0, trainer._updates0 = 0.0, 0, 0
    trainer.run_offline()
    assert trainer.counters.stage == "B2" and trainer.counters.updates == 0
    src = tmp_path / "src" / "checkpoints" / "stage1.pt"
    assert trainer.offline_progress.stop_reason.startswith(f"from {src}")
    assert trainer.offline_progress.updates == src_updates  # its record, not new updates
    theirs = torch.load(tmp_path / "src" / "checkpoints" / "stage1.pt", weights_only=False)["loss_module"]
    copy = torch.load(tmp_path / "run" / "checkpoints" / "stage1.pt", weights_only=False)["loss_module"]
    now = trainer.learner.loss_module.state_dict()
    online = [k for k in theirs if k.startswith("value_network_params")]
    assert online and all(torch.equal(theirs[k], copy[k]) and torch.equal(theirs[k], now[k])
                          and torch.equal(theirs[k], now["target_" + k]) for k in online)
    assert not trainer.learner.optimizer.state
    summary = train(compose_cfg("train", b + [f"mode.stage1.init={tmp_path / 'src'}"]),
                    tmp_path / "run2", demos=demos)
    from memrl.dqn.schedule import UpdateSchedule

    rounds = UpdateSchedule(4, 20).rounds_due  # TINY's train_every and warmup_frames
    assert source.updates == src_updates + rounds(source.frames)
    assert summary.updates == rounds(summary.frames)  # stage-2 updates only
    # another reward is allowed (stage 2 fits its Q-values to its own run's reward), logged
    from memrl.checkpoint import stage1_source

    other = compose_cfg("train", b + ["env.reward.collision=-50"])
    with caplog.at_level(logging.INFO, logger="memrl.checkpoint"):
        assert stage1_source(tmp_path / "src", other.env) == tmp_path / "src" / "checkpoints" / "stage1.pt"
    assert re.search(r"trained under the reward \{'collision': -5, .*; stage 2 trains under this run's "
                     r"\{'collision': -50, ", caplog.text)
    shaped = compose_cfg("train", b + ["env.shaping.weight=2.0"])  # shaping is reward too
    with caplog.at_level(logging.INFO, logger="memrl.checkpoint"):
        assert stage1_source(tmp_path / "src", shaped.env).name == "stage1.pt"
    assert re.search(r"\(shaping off\); stage 2 trains under this run's .*\(shaping \{'weight': 2, ",
                     caplog.text)
    # refused at start, one line each, no run folder left
    for overrides, match in (
            ([f"mode.stage1.init={tmp_path / 'nothing'}"], "no stage-1 network"),
            (["env.duration=31", f"mode.stage1.init={tmp_path / 'src'}"], "another env config")):
        with pytest.raises(ValueError, match=f"config 'mode.stage1.init': .*{match}"):
            train(compose_cfg("train", tiny("B") + [*overrides]), tmp_path / "bad", demos=demos)
        assert not (tmp_path / "bad").exists()
    # like every stage-1 key, Default has none: refused at composition, naming the mode that has it
    # (a study's train overrides and variants give each mode only its own keys: tests/test_study.py)
    with pytest.raises(HydraException) as err:
        compose_cfg("train", TINY + [f"mode.stage1.init={tmp_path / 'nothing'}"])
    assert one_line(err.value) == ("config 'mode.stage1.init': mode default has no such key "
                                   "(mode B's key: add +mode=B)")


class Killed(RuntimeError):
    pass


@pytest.mark.parametrize(("mode", "overlap"), [(None, True), (None, False), ("A", True)])
def test_killed_and_resumed_run_equals_an_uninterrupted_one(compose_cfg, tmp_path, demos,
                                                            monkeypatch, mode, overlap):
    extra = ["total_episodes=6", "checkpoint_every=2", f"agent.overlap={overlap}"]
    cfg = compose_cfg("train", tiny(mode) + extra)
    full = train(cfg, tmp_path / "full", demos=demos)

    # Kill after episode 5: episodes 5 was done after the checkpoint at 4 and is redone.
    original = Trainer._episodes_done

    def dying(self, ends):
        original(self, ends)
        if self.counters.episodes == 5:
            raise Killed("simulated kill")

    monkeypatch.setattr(Trainer, "_episodes_done", dying)
    with pytest.raises(Killed):
        train(cfg, tmp_path / "cut", demos=demos)
    monkeypatch.setattr(Trainer, "_episodes_done", original)
    assert len(rows(tmp_path / "cut" / "episodes.csv")) == 5
    before = ckpt.load_state(tmp_path / "cut" / "checkpoints" / "last")["wall_s"]
    resumed_cfg = compose_cfg("train", tiny(mode) + extra + [f"resume={tmp_path / 'cut'}"])
    resumed = train(resumed_cfg, demos=demos)

    assert resumed.resumed_from_episode == 4
    # the run's training time: the killed call's up to its checkpoint, then this call's
    assert before > 0 and resumed.train_wall_s == before + resumed.wall_s
    assert full.train_wall_s == full.wall_s
    for key in ("frames", "episodes", "updates", "stage"):
        assert getattr(resumed, key) == getattr(full, key), key
    assert rows(tmp_path / "cut" / "episodes.csv") == rows(tmp_path / "full" / "episodes.csv")
    assert rows(tmp_path / "cut" / "updates.csv")[-1]["loss"] == rows(
        tmp_path / "full" / "updates.csv")[-1]["loss"]
    sa = ckpt.load_state(tmp_path / "full" / "checkpoints" / "last")
    sb = ckpt.load_state(tmp_path / "cut" / "checkpoints" / "last")
    assert sa["counters"] == sb["counters"]
    assert_same_final_weights_and_agent_buffers(cfg, demos, tmp_path / "full", tmp_path / "cut")


def test_mode_b_on_n_envs_killed_in_stage_1_resumes_exactly(compose_cfg, tmp_path, demos,
                                                            monkeypatch):
    """A checkpoint made in stage 1 holds no collector state (its envs have not started): with
    N > 1 envs the resumed run starts stage 2 on fresh envs, as the uninterrupted run does."""
    cfg = compose_cfg("train", tiny("B") + ["env.num_envs=2", "total_episodes=null",
                                       "total_frames=48", "mode.stage1.criterion=max_updates"])
    full = train(cfg, tmp_path / "full", demos=demos)
    original = Trainer.save_checkpoint

    def dying(self):
        original(self)
        if self.counters.stage == "B1" and self.offline_progress.updates == 8:
            raise Killed("simulated kill")

    monkeypatch.setattr(Trainer, "save_checkpoint", dying)
    with pytest.raises(Killed):
        train(cfg, tmp_path / "cut", demos=demos)
    monkeypatch.setattr(Trainer, "save_checkpoint", original)
    resumed = train(compose_cfg("train", tiny("B") + [
        "env.num_envs=2", "total_episodes=null", "total_frames=48",
        "mode.stage1.criterion=max_updates", f"resume={tmp_path / 'cut'}"]), demos=demos)
    assert resumed.stage1["updates"] == full.stage1["updates"] == 12
    assert (resumed.frames, resumed.episodes, resumed.updates) == (full.frames, full.episodes, full.updates)
    assert rows(tmp_path / "cut" / "episodes.csv") == rows(tmp_path / "full" / "episodes.csv")
    assert_same_final_weights_and_agent_buffers(cfg, demos, tmp_path / "full", tmp_path / "cut")


def test_resume_refuses_a_checkpoint_from_another_config(compose_cfg, tmp_path):
    cfg = compose_cfg("train", TINY + ["total_episodes=1"])
    train(cfg, tmp_path)
    other = compose_cfg("train", TINY + ["total_episodes=2", "agent.lr=0.1", f"resume={tmp_path}"])
    with pytest.raises(ckpt.CheckpointError, match="agent.lr"):
        train(other)


OLD_UNION = {"demos_path": None, "demo_fraction": 0.3, "margin_weight": 2.0, "sampling": "proportional",
             "example": {"episodes": 7},
             "stage1": {"max_updates": 7, "lr": 0.01, "margin": 0.8, "init": None},
             "stage2": {"demo_fraction": 0.2, "eps_start": 0.5}}
"""Keys of every mode, as the ``mode`` node of a run made before each mode had its own schema
held them (at values other than the defaults)."""


def with_old_union(mode: dict) -> dict:
    """``mode`` as an older run stored it: its own values, plus every other mode's keys."""
    def merge(old: dict, own: dict) -> dict:
        return {**old, **{k: merge(old[k], v) if isinstance(v, dict) and isinstance(old.get(k), dict)
                          else v for k, v in own.items()}}
    return merge(OLD_UNION, mode)


def test_a_default_run_made_when_the_mode_node_held_every_modes_keys_resumes(compose_cfg, tmp_path):
    """Default has no prior-knowledge key (giving one is refused at composition, naming the mode
    that has it); a run made when its ``mode`` node held them all resumes: they are not its
    keys. A change to an A run's own key is refused, naming the key."""
    train(compose_cfg("train", TINY + ["total_episodes=1"]), tmp_path)
    state_file = tmp_path / "checkpoints" / "last" / "state.pt"
    state = torch.load(state_file, weights_only=False)
    state["config"]["mode"] = with_old_union(state["config"]["mode"])
    torch.save(state, state_file)
    ckpt.write_manifest(state_file.parent)
    resumed = train(compose_cfg("train", TINY + ["total_episodes=2", f"resume={tmp_path}"]))
    assert resumed.resumed_from_episode == 1 and resumed.episodes == 2
    cfg = compose_cfg("train", TINY + ["total_episodes=1", "+mode=A"])
    other = compose_cfg("train", TINY + ["total_episodes=1", "+mode=A", "mode.demo_fraction=0.3"])
    diff = ckpt.config_diff(ckpt.used(ckpt.comparable(cfg)), ckpt.used(ckpt.comparable(other)))
    assert diff == ["mode.demo_fraction: 0.1 (checkpoint) vs 0.3 (now)"]


def test_an_older_a_run_s_margin_under_its_old_name_is_read_as_mode_margin(compose_cfg):
    """Mode A's margin was ``mode.stage1.margin``: a run that stored it there compares as if it
    had stored ``mode.margin`` (same value: no difference; another: a difference in
    ``mode.margin``), so it resumes and shares report rows with a new run."""
    base = tiny("A") + ["total_episodes=1"]
    now = ckpt.comparable(compose_cfg("train", base))
    assert "stage1" not in now["mode"] and now["mode"]["margin"] == 0.8

    def stored_as_before(margin: float) -> dict:
        mode = {k: v for k, v in now["mode"].items() if k != "margin"}
        return {**now, "mode": {**mode, "stage1": {"margin": margin}}}

    assert ckpt.config_diff(ckpt.used(stored_as_before(0.8)), ckpt.used(now)) == []
    assert ckpt.config_diff(ckpt.used(stored_as_before(0.5)), ckpt.used(now)) == [
        "mode.margin: 0.5 (checkpoint) vs 0.8 (now)"]
    half = ckpt.comparable(compose_cfg("train", base + ["mode.margin=0.5"]))
    assert ckpt.config_diff(ckpt.used(stored_as_before(0.5)), ckpt.used(half)) == []


@pytest.mark.parametrize(("mode", "read"), [("A", "mode.margin=0.5"),
                                            ("B", "mode.stage1.max_updates=7")])
def test_a_prior_knowledge_run_ignores_the_other_modes_keys_of_an_older_run(compose_cfg, mode, read):
    """Mode A has no stage key but the margin of its margin loss; mode B not A's two keys: the
    values an older run's union ``mode`` node held for those keep the config the same for
    resuming and for report rows; a change to a key of the mode's own is a difference."""
    base = tiny(mode) + ["total_episodes=1"]
    now = ckpt.comparable(compose_cfg("train", base))
    old = {**now, "mode": with_old_union(now["mode"])}
    assert set(old["mode"]) > set(now["mode"])
    assert ckpt.config_diff(ckpt.used(old), ckpt.used(now)) == []
    key, value = read.split("=")
    other = ckpt.used(ckpt.comparable(compose_cfg("train", base + [read])))
    assert [d.split(":")[0] for d in ckpt.config_diff(ckpt.used(old), other)] == [key]


def test_checkpoint_from_before_the_speed_keys_resumes_with_their_old_values(compose_cfg,
                                                                            tmp_path):
    """A checkpoint whose config predates agent.precision/agent.overlap: resuming it with the
    new defaults is refused naming both; with the old behaviour's values it resumes."""
    legacy = ["agent.precision=float32", "agent.overlap=false", "env.bev.path_time=0"]
    train(compose_cfg("train", TINY + ["total_episodes=1", *legacy]), tmp_path)
    state_file = tmp_path / "checkpoints" / "last" / "state.pt"
    state = torch.load(state_file, weights_only=False)
    for key in ("precision", "overlap"):
        del state["config"]["agent"][key]
    del state["config"]["env"]["bev"]["path_time"]
    del state["config"]["env"]["bev"]["path_length"]  # an older key, at today's default: no difference
    state["config"]["mode"]["stage1"] = {"max_updates": 30000}  # its mode node held every mode's keys
    del state["wall_s"]  # and the record of the run's training time
    torch.save(state, state_file)
    (state_file.parent / ckpt.MANIFEST).unlink()  # such checkpoints predate the manifest too
    with pytest.raises(ckpt.CheckpointError, match=ckpt.MANIFEST):  # unverifiable: refused
        train(compose_cfg("train", TINY + ["total_episodes=2", f"resume={tmp_path}", *legacy]))
    ckpt.write_manifest(state_file.parent)  # the way the refusal names, for files known good
    with pytest.raises(ckpt.CheckpointError, match="agent.overlap") as err:
        train(compose_cfg("train", TINY + ["total_episodes=2", f"resume={tmp_path}"]))
    assert "agent.precision: 'float32' (checkpoint) vs 'auto' (now)" in str(err.value)
    # keys older than those are compared at what the versions before them did
    assert "env.bev.path_time: 0.0 (checkpoint) vs 2.0 (now)" in str(err.value)
    assert "mode.stage1" not in str(err.value)  # a Default run never reads it
    assert "path_length" not in str(err.value)
    resumed = train(compose_cfg("train", TINY + ["total_episodes=2", f"resume={tmp_path}",
                                                 *legacy]))
    assert resumed.resumed_from_episode == 1 and resumed.episodes == 2
    assert resumed.train_wall_s is None  # the earlier call's time is unknown, not 0


def test_checkpoint_from_before_the_demo_recipe_asks_for_the_old_example(compose_cfg, tmp_path,
                                                                          demos):
    """A checkpoint without ``mode.example`` used the old example (10 whole noiseless episodes):
    a mode A run that recorded its demos is refused naming the recipe's keys; a Default run,
    which records none, resumes as it is."""
    for mode, run in (("A", tmp_path / "a"), ("default", tmp_path / "d")):
        extra = ["+mode=A"] if mode == "A" else []
        train(compose_cfg("train", TINY + ["total_episodes=1", *extra]), run, demos=demos)
        state_file = run / "checkpoints" / "last" / "state.pt"
        state = torch.load(state_file, weights_only=False)
        # an older checkpoint: its mode node held every mode's keys, but no example yet
        older = with_old_union(state["config"]["mode"])
        state["config"]["mode"] = {k: v for k, v in older.items() if k != "example"}
        torch.save(state, state_file)
        ckpt.write_manifest(state_file.parent)  # re-manifested as the refusal says
        again = compose_cfg("train", TINY + ["total_episodes=2", f"resume={run}", *extra])
        if mode == "A":
            with pytest.raises(ckpt.CheckpointError, match="mode.example") as err:
                train(again, demos=demos)
            assert "mode.example.episodes: 10 (checkpoint) vs 12 (now)" in str(err.value)
            assert "mode.example.action_noise: 0.0 (checkpoint) vs 0.2 (now)" in str(err.value)
            old_example = ["mode.example.episodes=10", "mode.example.tail_steps=null",
                           "mode.example.action_noise=0", "mode.example.driver.merge_window=null",
                           "mode.example.driver.speed_tolerance=null",
                           "mode.example.env.initial_lane=null",
                           "mode.example.env.vehicles_count=null"]
            assert train(compose_cfg("train", TINY + ["total_episodes=2", f"resume={run}", *extra,
                                                      *old_example]),
                         demos=demos).resumed_from_episode == 1
        else:
            assert train(again).resumed_from_episode == 1


def test_resume_needs_a_complete_checkpoint(compose_cfg, tmp_path):
    (tmp_path / "checkpoints" / "last").mkdir(parents=True)
    cfg = compose_cfg("train", TINY + [f"resume={tmp_path}"])
    with pytest.raises(ckpt.CheckpointError, match="no complete checkpoint"):
        train(cfg)


@pytest.mark.parametrize(("override", "key"), [("agent.gamma=1.5", "agent.gamma"),
                                               ("+mode=A mode.sampling=random", "mode.sampling"),
                                               ("agent.eps_start=0.01", "agent.eps_start"),
                                               ("+mode=B mode.stage1.lr=0", "mode.stage1.lr")])
def test_bad_training_values_name_the_key(compose_cfg, tmp_path, override, key):
    """Each mode checks the keys it reads (memrl.modes), the agent's keys are checked always."""
    cfg = compose_cfg("train", TINY + override.split())
    with pytest.raises(UserError, match=f"config '{key.replace('.', '[.]')}'"):
        train(cfg, tmp_path)


def test_finished_run_loads_as_a_greedy_policy(compose_cfg, tmp_path):
    from memrl.checkpoint import load_policy, load_qnet
    from memrl.envs.torchrl_env import make_env, unwrap

    cfg = compose_cfg("train", TINY + ["total_episodes=1"])
    train(cfg, tmp_path)
    net, env_cfg = load_qnet(tmp_path)
    assert env_cfg["duration"] == 30
    policy = load_policy(str(tmp_path))
    env = make_env(env_cfg, seed=0)
    pixels = env.reset()["pixels"]
    assert policy.act(unwrap(env), pixels.numpy()) == int(net(pixels).argmax())
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ckpt.CheckpointError, match="bad.pt"):
        load_policy(str(tmp_path / "bad.pt"))


def test_periodic_evaluation_rows_during_training(compose_cfg, tmp_path):
    cfg = compose_cfg("train", TINY + ["total_episodes=2", "eval.every=2", "eval.episodes=2"])
    train(cfg, tmp_path)
    evals = rows(tmp_path / "eval_periodic.csv")
    assert [int(r["episode"]) for r in evals] == [2]
    assert 0 <= float(evals[0]["survival_random"]) <= 100


def test_periodic_evaluation_by_env_steps_trains_the_same_weights(compose_cfg, tmp_path):
    """``eval.unit=env_steps``: a row at the first step past each multiple of ``every``; the
    weights and episodes equal those of a run without periodic evaluation, and a run resumes
    under another schedule (``eval`` is a runtime key)."""
    base = TINY + ["total_episodes=null", "total_frames=120", "env.num_envs=4", "eval.episodes=1"]
    train(compose_cfg("train", base + ["eval.every=50", "eval.unit=env_steps"]), tmp_path / "on")
    train(compose_cfg("train", base + ["eval.every=0"]), tmp_path / "off")
    # a checkpoint from before eval was a runtime key stored it: not compared either
    state_file = tmp_path / "off" / "checkpoints" / "last" / "state.pt"
    state = torch.load(state_file, weights_only=False)
    state["config"]["eval"] = {"every": 100, "episodes": 10}
    torch.save(state, state_file)
    ckpt.write_manifest(state_file.parent)  # edited on purpose: its manifest written again
    steps = [int(r["env_steps"]) for r in rows(tmp_path / "on" / "eval_periodic.csv")]
    # 4 envs add 4 env steps per step, and a round is due every 4 (agent.train_every): the
    # first multiple of 4 at or past 50, then 100 itself
    assert steps == [52, 100]
    a, b = (torch.load(tmp_path / n / "checkpoints" / "final.pt", weights_only=False)["qnet"]
            for n in ("on", "off"))
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert rows(tmp_path / "on" / "episodes.csv") == rows(tmp_path / "off" / "episodes.csv")
    more = [o for o in base if not o.startswith("total_frames")] + [
        "total_frames=160", "eval.every=1", f"resume={tmp_path / 'off'}"]
    assert train(compose_cfg("train", more)).frames == 160


def test_overlapped_collection_is_deterministic_and_keeps_the_schedule(compose_cfg, tmp_path):
    """Two overlapped runs are identical (the learner thread's loss must not switch the
    acting thread's exploration off), and every mode keeps the update schedule."""
    base = TINY + ["total_episodes=4", "agent.warmup_frames=8"]
    runs = [train(compose_cfg("train", base + [f"agent.overlap={o}"]), tmp_path / f"{o}_{i}")
            for i, o in enumerate([True, True, False])]
    a, b = (torch.load(tmp_path / name / "checkpoints" / "final.pt", weights_only=False)["qnet"]
            for name in ("True_0", "True_1"))
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert rows(tmp_path / "True_0" / "episodes.csv") == rows(tmp_path / "True_1" / "episodes.csv")
    assert runs[0].updates == runs[1].updates > 0
    # Same schedule either way: one update at every 4th env step from step 8 (warm-up) on.
    for run in runs:
        assert run.updates == run.frames // 4 - 1


def test_stage1_agreement_parts_split_speed_and_curvature():
    """A network that always picks action 3 (keep speed, curvature -1) against demo actions
    4 (idle), 3, 5 (keep speed, curvature +1) and 1 (slow down, keep curvature)."""
    from tensordict import TensorDict

    from memrl.dqn.stage1 import agreement, agreement_parts
    from memrl.envs.vehicles import ACTIONS

    assert [ACTIONS[i] for i in (4, 3, 5, 1)] == [(0, 0), (0, -1), (0, 1), (-1, 0)]

    class Always3(torch.nn.Module):
        def forward(self, pixels):
            return torch.nn.functional.one_hot(torch.full(pixels.shape[:1], 3), 9).float()

    held = TensorDict({"pixels": torch.zeros(4, 4, 84, 84, dtype=torch.uint8),
                       "action": torch.tensor([4, 3, 5, 1])}, [4])
    assert agreement(Always3(), held) == 0.25
    assert agreement_parts(Always3(), held, chunk=3) == {
        "speed": 0.75, "curvature": 0.25, "steering_recall": 0.5, "steering_share": 1.0,
        "greedy_actions": 1.0}


def test_stage1_check_warns_once_the_greedy_action_no_longer_depends_on_the_state(caplog):
    """A network whose greedy action is the same on every held-out state (what a stage 1 whose
    ReLU units died looks like) gets one warning line at the check; one that tells the states
    apart (greedy action = the first pixel's value) gets none and counts its actions."""
    import logging

    from omegaconf import OmegaConf
    from tensordict import TensorDict

    from memrl.dqn.stage1 import Stage1Checks, Stage1Progress

    class Always3(torch.nn.Module):
        def forward(self, pixels):
            return torch.nn.functional.one_hot(torch.full(pixels.shape[:1], 3), 9).float()

    class FirstPixel(torch.nn.Module):
        def forward(self, pixels):
            return torch.nn.functional.one_hot(pixels[:, 0, 0, 0].long(), 9).float()

    pixels = torch.zeros(5, 4, 84, 84, dtype=torch.uint8)
    pixels[:, 0, 0, 0] = torch.tensor([0, 4, 4, 7, 8])
    held = TensorDict({"pixels": pixels, "action": torch.tensor([4, 3, 5, 1, 4])}, [5])
    cfg = OmegaConf.create({"drive_episodes": 0, "max_updates": 100, "criterion": "max_updates",
                            "check_every": 10, "keep_best": True})
    for net, distinct, warned in ((Always3(), 1.0, True), (FirstPixel(), 4.0, False)):
        caplog.clear()
        progress = Stage1Progress(updates=10)
        with caplog.at_level(logging.WARNING, logger="memrl.dqn.stage1"):
            metrics = Stage1Checks(cfg, {}, held, progress).check(net, torch.nn.Linear(1, 1), [1.0])
        assert metrics["agreement_greedy_actions"] == distinct
        lines = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        assert lines == (["stage 1: 10 updates: the greedy action is the same on all 5 held-out demo "
                          "states: the network's output does not depend on its input (collapsed, "
                          "e.g. dead ReLU units: python -m memrl.tools.stage1_probe); it may not recover"]
                         if warned else [])


class ScriptedDrives:
    """Stands in for ``drive_check``: returns the given ``both`` counts in turn and keeps a
    copy of the weights it was shown."""

    def __init__(self, both):
        self.both, self.seen = list(both), []

    def __call__(self, qnet, env_cfg, episodes, seed=0):
        self.seen.append({k: v.clone() for k, v in qnet.state_dict().items()})
        both = self.both.pop(0)
        return {"survived": both, "reached": both, "both": both}


def _stage1(compose_cfg, tmp_path, demos, monkeypatch, drives, extra):
    import memrl.dqn.stage1 as stage1

    monkeypatch.setattr(stage1, "drive_check", drives)
    cfg = compose_cfg("train", tiny("B") + ["mode.stage1.drive_episodes=4", *extra])
    trainer = Trainer(cfg, tmp_path, demos)
    trainer._t_start, trainer._frames0, trainer._updates0 = 0.0, 0, 0
    return trainer


def test_stage1_keeps_the_weights_that_drove_best(compose_cfg, tmp_path, demos, monkeypatch):
    drives = ScriptedDrives([1, 3, 2])  # checks at 4, 8, 12 updates
    trainer = _stage1(compose_cfg, tmp_path, demos, monkeypatch, drives,
                      ["mode.stage1.criterion=max_updates", "mode.stage1.lr=0.003"])
    trainer.run_offline()
    s1 = trainer.offline_progress
    assert [d["updates"] for d in s1.drives] == [4, 8, 12] and s1.best_updates == 8
    assert "weights of update 8" in s1.stop_reason
    best, last = drives.seen[1], drives.seen[2]
    assert any(not torch.equal(best[k], last[k]) for k in best)  # training went on after 8
    saved = torch.load(tmp_path / "checkpoints" / "stage1.pt", weights_only=False)["loss_module"]
    now = trainer.learner.qnet.state_dict()
    for k, v in best.items():  # stage 2 and stage1.pt hold update 8's weights
        assert torch.equal(now[k], v)
    online = [k for k in saved if k.startswith("value_network_params")]
    assert online and all(torch.equal(saved[k], trainer.learner.loss_module.state_dict()[k])
                          for k in online)


def test_stage1_behaviour_criterion_stops_when_the_drives_reach_the_target(
        compose_cfg, tmp_path, demos, monkeypatch):
    drives = ScriptedDrives([1, 2, 4])
    trainer = _stage1(compose_cfg, tmp_path, demos, monkeypatch, drives,
                      ["mode.stage1.criterion=behaviour", "mode.stage1.drive_target=0.5",
                       "mode.stage1.max_updates=100"])
    trainer.run_offline()
    # 2 of 4 >= 0.5 at the second check; the last weights are the best: no swap
    p = trainer.offline_progress
    assert p.updates == 8 and p.stop_reason.startswith("behaviour")
    assert "weights of update" not in p.stop_reason
    assert trainer.counters.stage == "B2" and drives.both == [4]


def test_stage1_behaviour_criterion_needs_drive_episodes(compose_cfg, tmp_path):
    cfg = compose_cfg("train", tiny("B") + ["mode.stage1.criterion=behaviour"])
    with pytest.raises(UserError, match=r"mode\.stage1\.drive_episodes"):
        train(cfg, tmp_path)


def test_stage1_resumed_mid_way_keeps_its_best_weights(compose_cfg, tmp_path, demos, monkeypatch):
    extra = ["mode.stage1.criterion=max_updates", "mode.stage1.lr=0.003"]
    full = _stage1(compose_cfg, tmp_path / "full", demos, monkeypatch, ScriptedDrives([3, 1, 2]),
                   extra)
    full.run_offline()
    cut = _stage1(compose_cfg, tmp_path / "cut", demos, monkeypatch, ScriptedDrives([3, 1]), extra)

    def die(updates):
        if updates == 10:
            raise Killed("simulated kill")

    with pytest.raises(Killed):
        cut.run_offline(die)  # last checkpoint at 8 updates; best so far: update 4
    resumed = _stage1(compose_cfg, tmp_path / "cut", demos, monkeypatch, ScriptedDrives([2]), extra)
    resumed.resume(tmp_path / "cut")
    assert resumed.offline_progress.updates == 8 and resumed.offline_progress.best_updates == 4
    resumed.run_offline()
    assert resumed.offline_progress.best_updates == full.offline_progress.best_updates == 4
    assert resumed.offline_progress.drives == full.offline_progress.drives
    a, b = full.learner.loss_module.state_dict(), resumed.learner.loss_module.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_drive_check_counts_the_behaviour_in_its_own_scenes(compose_cfg):
    from memrl.dqn.stage1 import drive_check
    from memrl.envs.vehicles import IDLE, N_ACTIONS
    from memrl.evaluation.protocol import scenario_seeds

    class KeepLane(torch.nn.Module):  # argmax Q = keep speed and curvature, always
        def forward(self, x):
            q = torch.zeros(len(x), N_ACTIONS)
            q[:, IDLE] = 1.0
            return q

    cfg = compose_cfg("train", TINY)
    counts = drive_check(KeepLane(), cfg.env, 6, seed=0)
    # a non-goal start and no steering: the target lane is never reached
    assert counts["reached"] == counts["both"] == 0 and 0 <= counts["survived"] <= 6
    assert counts == drive_check(KeepLane(), cfg.env, 6, seed=0)
    assert not set(scenario_seeds(0, 20, "stage1")) & set(scenario_seeds(0, 100, "test"))


@pytest.mark.parametrize("mode, stage, overrides, weight", [
    ("A", "A", [], 3.0),
    ("A", "A", ["mode.margin_weight=0"], 0.0),  # the paper's A: eq. (1) alone
    ("B", "B2", ["mode.stage2.demo_fraction=0.25"], 3.0),
    ("B", "B2", ["mode.stage2.demo_fraction=0.25", "mode.stage2.margin_weight=0"], 0.0),
    ("B", "B2", ["mode.stage2.demo_fraction=0.25", "mode.stage2.margin_weight=2"], 2.0),
    ("B", "B1", ["mode.stage1.margin_weight=3", "mode.stage2.demo_fraction=0.25",
                 "mode.stage2.margin_weight=2"], 3.0),
])
def test_each_stage_sets_its_own_margin_weight(compose_cfg, demos, mode, stage, overrides, weight):
    from memrl.dqn.builder import StageInputs, build_stage
    from memrl.losses import MarginTerm, TDTerm
    from memrl.modes import mode_of

    margin = "mode.margin=0.6" if mode == "A" else "mode.stage1.margin=0.6"  # each mode's key
    cfg = compose_cfg("train", tiny(mode) + [margin] + overrides)
    built = build_stage(mode_of(cfg).stage(stage), StageInputs.of(cfg), demos, 1, torch.device("cpu"))
    assert built.terms == ((TDTerm(),) if weight == 0 else (TDTerm(), MarginTerm(weight, 0.6)))


def test_stage2_keeps_prior_knowledge_at_its_stratified_share(compose_cfg, tmp_path, demos):
    cfg = compose_cfg("train", tiny("B") + ["mode.stage2.demo_fraction=0.25"])
    summary = train(cfg, tmp_path, demos=demos)
    assert summary.stage == "B2"
    stage2 = [r for r in rows(tmp_path / "updates.csv") if r["stage"] == "B2"]
    # exactly round(0.25 x 8) = 2 demos in every stage-2 batch
    assert stage2 and {(r["demo_count_min"], r["demo_count_max"]) for r in stage2} == {("2", "2")}
    # the paper's B (0) has none, whatever the margin weight (nothing for it to act on)
    paper_b = compose_cfg("train", tiny("B") + ["mode.stage2.demo_fraction=0"])
    assert paper_b.mode.stage2.margin_weight == 3
    train(paper_b, tmp_path / "paper_b", demos=demos)
    stage2 = [r for r in rows(tmp_path / "paper_b" / "updates.csv") if r["stage"] == "B2"]
    assert stage2 and {(r["demo_count_min"], r["demo_count_max"]) for r in stage2} == {("0", "0")}


def test_a_finished_run_resumed_with_a_bigger_budget_ends_as_an_uninterrupted_one(compose_cfg, tmp_path,
                                                                                  demos):
    """``resume=<finished run> total_frames=<more>``: it trains on from its last checkpoint to
    the weights and episodes of a run given the bigger budget from the start."""
    base = tiny("B") + ["total_episodes=null", "env.num_envs=2", "mode.stage1.criterion=max_updates"]
    full = train(compose_cfg("train", base + ["total_frames=96"]), tmp_path / "full", demos=demos)
    short = train(compose_cfg("train", base + ["total_frames=48"]), tmp_path / "ext", demos=demos)
    assert short.frames < full.frames
    more = train(compose_cfg("train", base + ["total_frames=96", f"resume={tmp_path / 'ext'}"]), demos=demos)
    assert more.resumed_from_episode == short.episodes
    for key in ("frames", "episodes", "updates", "stage"):
        assert getattr(more, key) == getattr(full, key), key
    assert rows(tmp_path / "ext" / "episodes.csv") == rows(tmp_path / "full" / "episodes.csv")
    assert_same_final_weights_and_agent_buffers(compose_cfg("train", base + ["total_frames=96"]), demos,
                                                tmp_path / "full", tmp_path / "ext")


def test_resuming_a_run_finished_at_this_budget_trains_nothing_and_keeps_its_files(compose_cfg, tmp_path):
    """A second process (a study's, or the user's) resuming a run another one has finished
    meanwhile returns the stored summary; before, it wrote summary.json again with its own
    1-second wall time. Another config is still refused."""
    cfg = compose_cfg("train", TINY + ["total_episodes=2"])
    first = train(cfg, tmp_path)
    files = ("summary.json", "episodes.csv", "updates.csv", "checkpoints/final.pt")
    before = {f: (tmp_path / f).read_bytes() for f in files}
    again = train(compose_cfg("train", TINY + ["total_episodes=2", f"resume={tmp_path}"]))
    assert again == first
    assert {f: (tmp_path / f).read_bytes() for f in files} == before
    with pytest.raises(ckpt.CheckpointError, match="agent.lr"):
        train(compose_cfg("train", TINY + ["total_episodes=2", "agent.lr=0.1", f"resume={tmp_path}"]))
