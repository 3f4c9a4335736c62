"""Training on N envs (the batched engine): every mode, the replay ratio, scenes that do not
depend on N, exact resume mid-episode, devices."""

from __future__ import annotations

import pytest
import torch

from memrl.checkpoint import resume as ckpt
from memrl.dqn.collector import Collector, episode_seed
from memrl.dqn.loop import Trainer
from memrl.dqn.schedule import UpdateSchedule
from memrl.errors import ConfigError
from memrl.train import train
from tests.helpers import TINY, assert_same_final_weights_and_agent_buffers, csv_rows, tiny

N4 = ["env.num_envs=4"]


rows = csv_rows


@pytest.mark.parametrize("mode", [None, "A", "B"])
def test_every_mode_trains_on_four_envs(compose_cfg, tmp_path, demos, mode):
    cfg = compose_cfg("train", tiny(mode) + N4 + ["total_episodes=8"])
    summary = train(cfg, tmp_path, demos=demos if mode else None)
    assert summary.num_envs == 4 and summary.episodes >= 8
    episodes = rows(tmp_path / "episodes.csv")
    assert [int(r["episode"]) for r in episodes] == list(range(1, summary.episodes + 1))
    # env steps are counted over all envs, 4 per batched step, and rows are in step order
    steps = [int(r["env_steps"]) for r in episodes]
    assert steps == sorted(steps) and all(s % 4 == 0 for s in steps)
    # the replay ratio is that of one env: a round at every 4th env step from warm-up (20) on
    schedule = UpdateSchedule(int(cfg.agent.train_every), int(cfg.agent.warmup_frames))
    online = summary.updates - (summary.stage1["updates"] if mode == "B" else 0)
    assert online == schedule.rounds_due(summary.frames)
    if mode == "A":
        assert {(r["demo_count_min"], r["demo_count_max"]) for r in rows(tmp_path / "updates.csv")} \
            == {("1", "1")}
    if mode == "B":
        assert summary.stage == "B2"


def test_update_schedule_counts():
    s = UpdateSchedule(train_every=4, warmup_frames=8)
    assert [s.rounds_due(f) for f in (0, 7, 8, 11, 12, 100)] == [0, 0, 1, 1, 2, 24]
    assert s.steps_to_next_round(0, 0, 1) == 8 and s.steps_to_next_round(0, 0, 16) == 1
    assert s.steps_to_next_round(16, 3, 16) == 1  # round 3 is due at 20
    assert UpdateSchedule(4, 0).rounds_due(4) == 1  # no warm-up: first round at step 4
    assert UpdateSchedule(4, 5).frames_of_round(0) == 8


def test_episode_k_has_the_same_scene_whatever_the_number_of_envs(compose_cfg):
    cfg = compose_cfg("train", TINY)
    single = Collector(cfg.env, 1, torch.device("cpu"), seed=3)
    batched = Collector(cfg.env, 4, torch.device("cpu"), seed=3)
    batched._reset_pending()
    first = batched.td["pixels"]
    for k in range(4):
        single.pending[:] = True
        single._reset_pending()
        assert torch.equal(single.td["pixels"], first[k]), k
    assert batched.started == single.started == 4
    assert episode_seed(3, 0) != episode_seed(3, 1)


class Killed(RuntimeError):
    pass


@pytest.mark.parametrize(("mode", "overlap"), [(None, True), (None, False), ("A", True), ("B", True)])
def test_killed_and_resumed_run_on_four_envs_equals_an_uninterrupted_one(
        compose_cfg, tmp_path, demos, monkeypatch, mode, overlap):
    extra = N4 + ["total_episodes=12", "checkpoint_every=3", f"agent.overlap={overlap}"]
    cfg = compose_cfg("train", tiny(mode) + extra)
    full = train(cfg, tmp_path / "full", demos=demos)

    original = Trainer._episodes_done
    seen: list[int] = []

    def dying(self, ends):
        original(self, ends)
        seen.append(self.counters.episodes)
        if self.counters.episodes >= 8:  # checkpoints fall mid-episode of the other envs
            raise Killed("simulated kill")

    monkeypatch.setattr(Trainer, "_episodes_done", dying)
    with pytest.raises(Killed):
        train(cfg, tmp_path / "cut", demos=demos)
    monkeypatch.setattr(Trainer, "_episodes_done", original)
    state = ckpt.load_state(tmp_path / "cut" / "checkpoints" / "last")
    assert 3 <= state["counters"]["episodes"] < 8 and bool(state["collector"]["engine"]["steps"].any())
    resumed = train(compose_cfg("train", tiny(mode) + extra + [f"resume={tmp_path / 'cut'}"]), demos=demos)

    for key in ("frames", "episodes", "updates", "stage"):
        assert getattr(resumed, key) == getattr(full, key), key
    assert rows(tmp_path / "cut" / "episodes.csv") == rows(tmp_path / "full" / "episodes.csv")
    assert rows(tmp_path / "cut" / "updates.csv") == [
        {**r, "updates_per_s": r2["updates_per_s"], "frames_per_s": r2["frames_per_s"]}
        for r, r2 in zip(rows(tmp_path / "full" / "updates.csv"),
                         rows(tmp_path / "cut" / "updates.csv"), strict=True)]
    assert_same_final_weights_and_agent_buffers(cfg, demos, tmp_path / "full", tmp_path / "cut")


def test_a_run_on_cpu_loads_for_evaluation(compose_cfg, tmp_path):
    from memrl.checkpoint import load_qnet

    cfg = compose_cfg("train", TINY + N4 + ["device=cpu", "total_episodes=4"])
    summary = train(cfg, tmp_path)
    assert summary.device == "cpu"
    net, env_cfg = load_qnet(tmp_path)
    assert env_cfg["num_envs"] == 4
    trainer = Trainer(cfg, tmp_path / "again")
    trainer.resume(tmp_path)
    saved, now = net.state_dict(), trainer.learner.qnet.state_dict()
    assert saved.keys() == now.keys() and all(torch.equal(saved[k], now[k]) for k in saved)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message where CUDA is absent")
def test_device_cuda_without_cuda_stops_with_one_clear_message(compose_cfg, tmp_path):
    cfg = compose_cfg("train", TINY + ["device=cuda"])
    with pytest.raises(ConfigError, match=r"config 'device': cuda: CUDA is not available"):
        train(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("bad", ["gpu", "cuda:x", "tpu"])
def test_a_device_that_is_not_one_names_the_key(compose_cfg, tmp_path, bad):
    cfg = compose_cfg("train", TINY + [f"device={bad}"])
    with pytest.raises(ConfigError, match=r"config 'device': expected auto, cpu, cuda or cuda:K"):
        train(cfg, tmp_path / "run")


def test_learned_cars_and_self_play_on_four_envs_resume_exactly(compose_cfg, tmp_path):
    from tests.helpers import save_pool

    pool = save_pool(tmp_path / "pool_src", seeds=(1,))
    extra = TINY + N4 + ["opponent=mixed", f"env.opponent.pool=[{pool[0]}]", "self_play_every=3",
                         "checkpoint_every=3", "agent.overlap=false"]
    full = train(compose_cfg("train", extra + ["total_episodes=10"]), tmp_path / "full")
    snaps = sorted(p.name for p in (tmp_path / "full" / "pool").iterdir())
    assert snaps == [f"episode_{k:07d}.pt" for k in range(3, full.episodes + 1, 3)]
    train(compose_cfg("train", extra + ["total_episodes=5"]), tmp_path / "cut")
    resumed = train(compose_cfg("train", extra + ["total_episodes=10", f"resume={tmp_path / 'cut'}"]))
    assert (resumed.frames, resumed.episodes, resumed.updates) == (full.frames, full.episodes, full.updates)
    assert rows(tmp_path / "cut" / "episodes.csv") == rows(tmp_path / "full" / "episodes.csv")
    trainer = Trainer(compose_cfg("train", extra + ["total_episodes=10"]), tmp_path / "cut")
    trainer.resume(tmp_path / "cut")  # the snapshots up to the checkpoint rejoin the pool
    assert len(trainer.collector.learned_controller().networks) == 1 + trainer.counters.episodes // 3


def test_the_opponent_pool_does_not_change_the_learners_initial_weights(compose_cfg, tmp_path):
    """Loading the pool's networks draws no random numbers: a run in mixed traffic starts from
    the same weights, and goes on with the same random stream (replay sampling), as the same
    seed with constant cars. Before, building the pool's networks moved the global generator,
    and mode B's stage 1 in mixed traffic started from other weights
    (docs/results/mixed_100k/stage1_flat/)."""
    from tests.helpers import save_pool

    pool = save_pool(tmp_path / "pool_src", seeds=(1, 2))
    runs = {}
    for name, extra in (("constant", []),
                        ("mixed", ["opponent=mixed", f"env.opponent.pool=[{pool[0]},{pool[1]}]"])):
        trainer = Trainer(compose_cfg("train", TINY + N4 + extra), tmp_path / name)
        runs[name] = (trainer, torch.get_rng_state())
    (constant, rng_constant), (mixed, rng_mixed) = runs["constant"], runs["mixed"]
    assert len(mixed.collector.learned_controller().networks) == 2
    a, b = constant.learner.qnet.state_dict(), mixed.learner.qnet.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert torch.equal(rng_constant, rng_mixed)
