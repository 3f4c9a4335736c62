"""K seeds of one configuration in one process (:func:`memrl.train.train_seeds`) write what their
own single-seed runs write, and a killed group resumes to the same runs."""

from __future__ import annotations

import json

import pytest
import torch

from memrl.dqn.loop import Trainer
from memrl.train import train, train_seeds
from tests.helpers import TINY, Killed, csv_rows, tiny_mode

SEEDS = (0, 1, 2)
WALL = ("updates_per_s", "frames_per_s")  # wall-clock columns of updates.csv


def updates_rows(run):
    return [{k: v for k, v in row.items() if k not in WALL} for row in csv_rows(run / "updates.csv")]


def assert_same_run(a, b, label) -> None:
    """Run folder ``b`` holds run ``a``'s episodes, update rows and final weights."""
    rows = csv_rows(a / "episodes.csv")
    assert len(rows) > 0 and rows == csv_rows(b / "episodes.csv"), label
    assert updates_rows(a) == updates_rows(b), label
    wa = torch.load(a / "checkpoints" / "final.pt", weights_only=False)["qnet"]
    wb = torch.load(b / "checkpoints" / "final.pt", weights_only=False)["qnet"]
    assert all(torch.equal(wa[k], wb[k]) for k in wa), label


def assert_same_runs(single, group):
    """Each seed's group run folder holds its single run's episodes, update rows and final weights."""
    for seed in SEEDS:
        assert_same_run(single / f"s{seed}", group / f"s{seed}", seed)
    episodes = [csv_rows(single / f"s{s}" / "episodes.csv") for s in SEEDS]
    assert all(episodes[i] != episodes[j] for i in range(len(SEEDS)) for j in range(i))  # the seeds differ


def when_seed_1_has(monkeypatch, episodes: int, act) -> None:
    """``act()`` after every batch of finished episodes of seed 1's run from ``episodes`` on."""
    original = Trainer._episodes_done

    def patched(self, ends):
        original(self, ends)
        if int(self.cfg.seed) == 1 and self.counters.episodes >= episodes:
            act()

    monkeypatch.setattr(Trainer, "_episodes_done", patched)


def singles(cfg, root, demos):
    for seed in SEEDS:
        c = cfg.copy()
        c.seed = seed
        train(c, root / f"s{seed}", demos=demos)


@pytest.mark.parametrize(("mode", "extra"), [(None, ["env.num_envs=4"]),
                                             (None, ["env.num_envs=4", "seeds_engine=shared"]),
                                             ("B", ["env.num_envs=4", "seeds_engine=shared"]),
                                             pytest.param("B", [], marks=pytest.mark.slow)])
def test_k_seeds_in_one_process_write_their_single_seed_runs(compose_cfg, tmp_path, demos, mode, extra,
                                                            monkeypatch):
    """Default on the batched engine (4 envs, an engine per seed or one for all: the seeds' runs
    in lockstep) and B (stage 1, then stage 2 on one shared engine, or on the reference env)."""
    from memrl.envs.shared_engine import SharedEngine

    cfg = compose_cfg("train", [*TINY, *tiny_mode(mode), *extra])
    singles(cfg, tmp_path / "single", demos)
    engines: list[SharedEngine] = []
    original = SharedEngine.__init__

    def keep(self, *args, **kwargs):
        original(self, *args, **kwargs)
        engines.append(self)

    monkeypatch.setattr(SharedEngine, "__init__", keep)
    summaries = train_seeds(cfg, SEEDS, tmp_path / "group", demos=demos)
    assert [s.seed for s in summaries] == list(SEEDS)
    assert_same_runs(tmp_path / "single", tmp_path / "group")
    if "seeds_engine=shared" in extra:  # one engine of 3 x 4 envs, one call per step of the longest run
        assert len(engines) == 1 and engines[0].engine.num_envs == 12
        assert engines[0].steps == max(s.frames for s in summaries) // 4
    else:
        assert engines == []


@pytest.mark.parametrize(("extra", "why"), [
    (["env.num_envs=1"], "shared needs env.num_envs > 1"),
    (["env.num_envs=4", "opponent=learned", "env.opponent.pool=[POOL]"], "shared: a shared engine takes no "
                                                                          "learned cars"),
])
def test_a_shared_engine_it_cannot_build_is_refused_in_one_line(compose_cfg, tmp_path, extra, why):
    from memrl.errors import ConfigError
    from tests.helpers import save_pool

    pool = save_pool(tmp_path / "pool", seeds=(1,))[0]
    cfg = compose_cfg("train", [*TINY, "seeds_engine=shared", *(e.replace("POOL", pool) for e in extra)])
    with pytest.raises(ConfigError, match=rf"config 'seeds_engine': {why}") as err:
        train_seeds(cfg, SEEDS, tmp_path / "group")
    assert "\n" not in str(err.value)
    assert not (tmp_path / "group").exists()


@pytest.mark.parametrize("engine", ["own", "shared"])
def test_a_killed_group_resumes_every_run_to_its_single_seed_run(compose_cfg, tmp_path, demos, monkeypatch,
                                                                 engine):
    """Shared: the runs' last checkpoints fall at different env steps, so the resumed group's
    slices hold frame rings saved at other heads than the shared engine's."""
    overrides = [*TINY, "env.num_envs=4", "total_episodes=12", "checkpoint_every=3", f"seeds_engine={engine}"]
    cfg = compose_cfg("train", overrides)
    singles(cfg, tmp_path / "single", demos)

    def kill():
        raise Killed("simulated kill")

    with monkeypatch.context() as patch:
        when_seed_1_has(patch, 8, kill)
        with pytest.raises(Killed):
            train_seeds(cfg, SEEDS, tmp_path / "group", demos=demos)
    assert not (tmp_path / "group" / "s1" / "summary.json").exists()
    if engine == "shared":
        from memrl.checkpoint import resume as ckpt

        saved = {ckpt.load_state(tmp_path / "group" / f"s{s}" / "checkpoints" / "last")["counters"]["frames"]
                 for s in SEEDS}
        assert len(saved) > 1  # the slices resume from different steps
    resumed = compose_cfg("train", [*overrides, f"resume={tmp_path / 'group'}"])
    summaries = train_seeds(resumed, SEEDS, demos=demos)
    done = [json.loads((tmp_path / "single" / f"s{s}" / "summary.json").read_text()) for s in SEEDS]
    assert [(s.episodes, s.frames, s.updates) for s in summaries] == [
        (d["episodes"], d["frames"], d["updates"]) for d in done]
    assert all(s.episodes >= 12 for s in summaries)
    assert_same_runs(tmp_path / "single", tmp_path / "group")


@pytest.mark.parametrize("engine", ["own", "shared"])
def test_a_stop_signal_saves_every_run_and_the_group_resumes_to_the_single_seed_runs(
        compose_cfg, tmp_path, demos, monkeypatch, engine):
    """SIGTERM while seed 1 takes its turn: every run of the group saves its checkpoint (not only
    the one that saw the signal), the group stops with Interrupted, and resuming it gives the
    single-seed runs (shared: each run goes on to the end of its iterate and saves there)."""
    import signal

    from memrl import stop

    overrides = [*TINY, "env.num_envs=4", "total_episodes=12", "checkpoint_every=100",
                 f"seeds_engine={engine}"]
    cfg = compose_cfg("train", overrides)
    singles(cfg, tmp_path / "single", demos)

    def signal_once():
        if stop.stop_requested() is None:
            signal.raise_signal(signal.SIGTERM)

    stop.install()
    try:
        with monkeypatch.context() as patch:
            when_seed_1_has(patch, 6, signal_once)
            with pytest.raises(stop.Interrupted):
                train_seeds(cfg, SEEDS, tmp_path / "group", demos=demos)
    finally:
        stop.uninstall()
    from memrl.checkpoint import resume as ckpt

    for seed in SEEDS:  # checkpoint_every=100: only the stop saved them, each past its start
        state = ckpt.load_state(tmp_path / "group" / f"s{seed}" / "checkpoints" / "last")
        assert 0 < state["counters"]["episodes"] < 12, seed
    resumed = compose_cfg("train", [*overrides, f"resume={tmp_path / 'group'}"])
    train_seeds(resumed, SEEDS, demos=demos)
    assert_same_runs(tmp_path / "single", tmp_path / "group")


def test_seeds_must_be_distinct(compose_cfg, tmp_path):
    from memrl.errors import ConfigError

    cfg = compose_cfg("train", TINY)
    with pytest.raises(ConfigError, match=r"config 'seeds': need distinct seeds, got \[0, 0\]"):
        train_seeds(cfg, [0, 0], tmp_path)
    assert not tmp_path.joinpath("s0").exists()


def test_the_command_trains_the_seeds_of_its_seeds_key(tmp_path):
    """``python -m memrl.train seeds=[3,4]``: one process, run folders s3 and s4 below its output dir."""
    import subprocess
    import sys

    out = tmp_path / "group"
    cmd = [sys.executable, "-m", "memrl.train", *TINY, "total_episodes=1", "seeds=[3,4]",
           f"hydra.run.dir={out}"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    for seed in (3, 4):
        summary = json.loads((out / f"s{seed}" / "summary.json").read_text())
        assert summary["seed"] == seed and summary["episodes"] == 1
        assert "seeds: null" in (out / f"s{seed}" / "config.yaml").read_text()


@pytest.mark.parametrize(("logger", "backend"), [("wandb", "W&B"), ("mlflow", "MLflow")])
def test_a_logger_of_one_run_per_process_is_refused_before_any_folder(compose_cfg, tmp_path, logger, backend):
    from memrl.errors import ConfigError

    cfg = compose_cfg("train", [*TINY, f"logger={logger}"])
    with pytest.raises(ConfigError, match=rf"config 'logger': logger={logger} keeps one active run per "
                                          rf"process \({backend}\)"):
        train_seeds(cfg, [0, 1], tmp_path / "group")
    assert not (tmp_path / "group").exists()
