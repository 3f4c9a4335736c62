"""Resume bookkeeping: one process per run folder, and a resumed run logs into the folder it continues."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

from memrl.run_lock import LOCK_NAME, RunFolderBusy, run_lock
from memrl.train import train
from tests.helpers import TINY

ROOT = Path(__file__).resolve().parents[1]


def digest(run_dir: Path) -> dict[str, str]:
    """Content hash of every file of a run folder but its lock."""
    return {str(p.relative_to(run_dir)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(run_dir.rglob("*")) if p.is_file() and p.name != LOCK_NAME}


def test_a_second_process_on_the_same_run_folder_is_refused(compose_cfg, tmp_path):
    train(compose_cfg("train", TINY + ["total_episodes=1"]), tmp_path)
    before = digest(tmp_path)
    resume = compose_cfg("train", TINY + ["total_episodes=2", f"resume={tmp_path}"])
    with run_lock(tmp_path):  # another process training (or resuming) in this folder
        with pytest.raises(RunFolderBusy) as err:
            train(resume)
        with pytest.raises(RunFolderBusy):  # a fresh run into that folder too
            train(compose_cfg("train", TINY + ["total_episodes=1"]), tmp_path)
    message = str(err.value)
    assert "\n" not in message and str(tmp_path) in message and "in use by another process" in message
    assert digest(tmp_path) == before  # nothing written, nothing lost
    assert train(resume).episodes == 2  # once the other process is gone, the resume runs


def test_the_lock_is_released_when_a_run_fails(compose_cfg, tmp_path, monkeypatch):
    from memrl.dqn.loop import Trainer

    def crash(self):
        raise RuntimeError("boom")

    monkeypatch.setattr(Trainer, "run", crash)
    with pytest.raises(RuntimeError, match="boom"):
        train(compose_cfg("train", TINY), tmp_path)
    with run_lock(tmp_path):
        pass


def test_a_resumed_run_writes_its_log_into_the_run_folder_it_continues(tmp_path):
    args = [o for o in TINY if o != "logger=none"] + ["logger=csv"]
    env = {**os.environ, "MEMRL_ROOT": str(tmp_path), "SDL_VIDEODRIVER": "dummy"}
    runs = tmp_path / "outputs" / "train" / "runs"

    def run(*extra: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "memrl.train", *args, *extra], cwd=ROOT,
                              env=env, capture_output=True, text=True, timeout=600)

    first = run("total_episodes=2")
    assert first.returncode == 0, first.stderr[-3000:]
    (run_dir,) = runs.iterdir()
    original_hydra = digest(run_dir / ".hydra")
    resumed = run("total_episodes=3", f"resume={run_dir}")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert list(runs.iterdir()) == [run_dir]  # no new runs/<time>/ folder
    log = (run_dir / "train.log").read_text()
    assert log.count("done: 2 episodes") == 1 and "resumed" in log and "done: 3 episodes" in log
    (resume_hydra,) = (run_dir / ".hydra").glob("resume_*")
    assert "resume=" in (resume_hydra / "overrides.yaml").read_text()
    assert {k: v for k, v in digest(run_dir / ".hydra").items()
            if not k.startswith("resume_")} == original_hydra  # the first start's files kept
