"""``study.seeds_per_process=K``: the study trains up to K seeds of one configuration per process
(:func:`memrl.train.train_group`), each run folder what its own single-seed run writes, a
finished run skipped, a killed group resumed."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from tests.helpers import TINY, Killed
from tests.test_seed_group import assert_same_run

SEEDS = (0, 1, 2)


def quoted(items):
    return "[" + ",".join(f"'{i}'" for i in items) + "]"


def study_cfg(compose_cfg, folder, seeds, per_process, train=TINY):
    return compose_cfg("study", [f"study.dir={folder}", "study.modes=[Default]", f"study.seeds={seeds}",
                                 f"study.train_overrides={quoted(train)}", "study.baselines=[]",
                                 "study.evaluate=none", "study.progress=false",
                                 f"study.seeds_per_process={per_process}"])


def test_process_groups_hold_consecutive_seeds_of_one_configuration(tmp_path):
    from memrl.studies.grid import Cell, process_groups

    grid = [Cell(m, "constant", s, tmp_path / f"{v}_{m}_constant_s{s}", [], OmegaConf.create({}), v)
            for v in ("x", "y") for m in ("Default", "B") for s in (0, 1, 2)]
    todo = [(c, c.seed == 1) for c in grid if not (c.variant == "y" and c.mode == "B" and c.seed == 0)]
    names = [[c.name for c, _ in g] for g in process_groups(todo, 2)]
    assert names == [["x_Default_constant_s0", "x_Default_constant_s1"], ["x_Default_constant_s2"],
                     ["x_B_constant_s0", "x_B_constant_s1"], ["x_B_constant_s2"],
                     ["y_Default_constant_s0", "y_Default_constant_s1"], ["y_Default_constant_s2"],
                     ["y_B_constant_s1", "y_B_constant_s2"]]
    assert [r for g in process_groups(todo, 2) for _, r in g] == [r for _, r in todo]  # resume flags kept
    assert [len(g) for g in process_groups(todo, 1)] == [1] * len(todo)
    assert [len(g) for g in process_groups(todo, 5)] == [3, 3, 3, 2]


def assert_single_runs(runs, single):
    for seed in SEEDS:
        name = f"Default_constant_s{seed}"
        assert_same_run(single / name, runs / name, seed)


@pytest.mark.parametrize("engine", ["own", "shared"])
def test_the_study_trains_k_seeds_per_process_and_resumes_a_killed_group(compose_cfg, tmp_path, monkeypatch,
                                                                          engine):
    """Seed 0 finished first on its own; then seeds 1 and 2 share one process (and with
    ``seeds_engine=shared`` one engine), are killed mid-way, and the same call again resumes
    that group: every run folder is its single run's, and each run's train.log holds its own
    lines (and the group's failure, naming both)."""
    import memrl.train
    from memrl.dqn.loop import Trainer
    from memrl.studies.grid import cells
    from memrl.study import study
    from memrl.train import train

    train_ = [*TINY, "total_episodes=6", "env.num_envs=2", f"seeds_engine={engine}"]
    folder = tmp_path / "s"
    for cell in cells(study_cfg(compose_cfg, folder, "[0,1,2]", 1, train_).study, folder / "runs"):
        train(cell.cfg, tmp_path / "single" / cell.name)
    first = study(study_cfg(compose_cfg, folder, "[0]", 2, train_))
    assert first.trained == ["Default_constant_s0"]

    groups: list[list[int]] = []
    real = memrl.train.train_group

    shared: list[bool] = []

    def recorded(cfgs, run_dirs, demos=None, shared_engine=False):
        groups.append([int(c.seed) for c in cfgs])
        shared.append(shared_engine)
        return real(cfgs, run_dirs, demos, shared_engine)

    monkeypatch.setattr(memrl.train, "train_group", recorded)
    original = Trainer._episodes_done

    def killed(self, ends):
        original(self, ends)
        if int(self.cfg.seed) == 2 and self.counters.episodes >= 3:
            raise Killed("simulated kill")

    with monkeypatch.context() as patch:
        patch.setattr(Trainer, "_episodes_done", killed)
        stopped = study(study_cfg(compose_cfg, folder, "[0,1,2]", 2, train_))
    assert stopped.skipped == ["Default_constant_s0"] and not stopped.trained
    assert list(stopped.failed) == ["Default_constant_s1", "Default_constant_s2"]
    assert set(stopped.failed.values()) == {"Killed: simulated kill"}
    again = study(study_cfg(compose_cfg, folder, "[0,1,2]", 2, train_))
    assert again.skipped == ["Default_constant_s0"]
    assert again.resumed == ["Default_constant_s1", "Default_constant_s2"] and not again.failed
    assert groups == [[1, 2], [1, 2]]  # one process for seeds 1 and 2, twice; seed 0 on its own
    assert shared == [engine == "shared"] * 2
    assert_single_runs(folder / "runs", tmp_path / "single")
    for seed, other in ((1, 2), (2, 1)):
        log = (folder / "runs" / f"Default_constant_s{seed}" / "train.log").read_text()
        assert f"Default_constant_s{seed}/summary.json" in log
        assert f"resumed {folder / 'runs' / f'Default_constant_s{seed}'}" in log
        naming = [line for line in log.splitlines() if f"Default_constant_s{other}" in line]
        assert naming and all("failed" in line for line in naming), naming  # only the group's kill


@pytest.mark.parametrize("per_process", [1, 3])
def test_seeds_per_process_is_in_the_typed_command_line(compose_cfg, tmp_path, per_process):
    from memrl.study import command_line

    cmd = command_line(study_cfg(compose_cfg, tmp_path, "[0,1]", per_process))
    assert f"study.seeds_per_process={per_process}" in cmd


def test_a_logger_of_one_run_per_process_keeps_the_study_at_one_seed_per_process(
        compose_cfg, tmp_path, caplog):
    from memrl.studies.grid import cells
    from memrl.study import seeds_per_process

    tb = study_cfg(compose_cfg, tmp_path, "[0,1]", 2, [*TINY, "logger=tensorboard"])
    assert seeds_per_process(tb, cells(tb.study, tmp_path / "runs")) == 2
    wb = study_cfg(compose_cfg, tmp_path, "[0,1]", 2, [*TINY, "logger=wandb"])
    assert seeds_per_process(wb, cells(wb.study, tmp_path / "runs")) == 1
    assert "study.seeds_per_process=2: one seed per process instead: logger=wandb keeps one" in caplog.text


def test_groups_train_in_spawned_processes_and_a_failing_run_fails_only_what_is_unfinished(tmp_path):
    import json
    import os

    from memrl.studies.grid import Cell, run_cells
    from tests.study_helpers import fake_group_trainer, fake_trainer

    grid = [Cell("Default", "constant", s, tmp_path / f"Default_constant_s{s}", [], OmegaConf.create({}))
            for s in (0, 1, 2, 3, 4)]
    seen: list[str] = []
    out = run_cells(grid, jobs=2, trainer=fake_trainer, finished=lambda c: seen.append(c.name),
                    per_process=2, group_trainer=fake_group_trainer)
    assert out.trained == ["Default_constant_s0", "Default_constant_s2", "Default_constant_s3",
                           "Default_constant_s4"]
    assert out.failed == {"Default_constant_s1": "RuntimeError: Default_constant_s1 diverged"}
    assert sorted(seen) == out.trained
    pid = {s: json.loads((tmp_path / f"Default_constant_s{s}" / "summary.json").read_text()).get("pid")
           for s in (0, 2, 3)}
    # s2 and s3 shared one process, a spawned worker (the pool may reuse s0's worker for them)
    assert pid[2] == pid[3] and None not in pid.values() and os.getpid() not in pid.values()
    assert "pid" not in json.loads((tmp_path / "Default_constant_s4" / "summary.json").read_text())  # alone
