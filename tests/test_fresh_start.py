"""A fresh start into a folder that holds a run is refused in one line and changes nothing;
``overwrite=true`` replaces the run; ``resume=`` continues it."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from memrl.errors import USAGE_EXIT, is_user_error, one_line
from memrl.run_folder import RunFolderTaken
from memrl.train import train
from tests.helpers import TINY, tree_hashes

ROOT = Path(__file__).resolve().parents[1]


def taken(run: Path) -> str:
    return (f"{run}: holds a training run already (config.yaml, checkpoints, summary.json, "
            f"episodes.csv); resume it with resume={run}, pick another folder, or replace it with "
            "overwrite=true")


@pytest.fixture
def run(smoke_run, tmp_path) -> Path:
    copy = tmp_path / "run"
    shutil.copytree(smoke_run, copy)
    return copy


def test_the_command_line_refuses_a_fresh_start_into_a_finished_run(run, tmp_path):
    before = tree_hashes(run)
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    env.update(MEMRL_ROOT=str(tmp_path), PYTHONPATH=str(ROOT))
    proc = subprocess.run([sys.executable, "-m", "memrl.train", "+experiment=smoke", "total_frames=50",
                           "progress=false", "seed=3", f"hydra.run.dir={run}"], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == USAGE_EXIT, proc.stderr
    assert [ln for ln in proc.stderr.splitlines() if ln.strip()] == [f"error: {taken(run)}"]
    assert tree_hashes(run) == before  # no .hydra/, no log lines, no replaced CSVs or weights


def test_train_refuses_a_fresh_start_into_a_run_and_overwrite_replaces_it(run, compose_cfg):
    (run / "eval").mkdir()
    (run / "eval" / "eval.json").write_text("{}\n")  # the earlier run's evaluation
    before = tree_hashes(run)
    with pytest.raises(RunFolderTaken) as info:
        train(compose_cfg("train", [*TINY, "total_episodes=1", "seed=3"]), run)
    assert is_user_error(info.value) and one_line(info.value) == taken(run)
    assert tree_hashes(run) == before
    summary = train(compose_cfg("train", [*TINY, "total_episodes=1", "seed=3", "overwrite=true"]), run)
    assert summary.seed == 3 and summary.episodes == 1
    assert not (run / "eval").exists()  # nothing of the earlier run passes for the new one's
    assert "seed: 3" in (run / "config.yaml").read_text().splitlines()


def test_a_finished_run_still_resumes(run, compose_cfg):
    assert train(compose_cfg("train", [*TINY, "total_episodes=3", f"resume={run}"])).episodes == 3


def test_a_folder_without_a_run_is_taken(tmp_path, compose_cfg):
    (tmp_path / "notes.txt").write_text("mine\n")
    train(compose_cfg("train", [*TINY, "total_episodes=1"]), tmp_path)
    assert (tmp_path / "notes.txt").read_text() == "mine\n"


def test_the_start_checks_know_the_folder_of_a_run_and_of_each_sweep_job(tmp_path):
    from omegaconf import OmegaConf

    from memrl.run_folder import planned_run_dir

    hydra = {"run": {"dir": str(tmp_path / "run")}, "job": {"num": 1},
             "sweep": {"dir": str(tmp_path / "sweep"), "subdir": "${hydra.job.num}"}}
    assert planned_run_dir(OmegaConf.create({"hydra": {**hydra, "mode": "RUN"}})) == tmp_path / "run"
    assert planned_run_dir(OmegaConf.create({"hydra": {**hydra, "mode": "MULTIRUN"}})) == \
        tmp_path / "sweep" / "1"
    assert planned_run_dir(OmegaConf.create({"seed": 0})) is None  # a Python caller's config
