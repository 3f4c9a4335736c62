"""SIGINT and SIGTERM stop a command cleanly: a resumable checkpoint, one line with the exact
resume command, exit status 128 + signal; the command as printed finishes equal to an
uninterrupted run."""

from __future__ import annotations

import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from tests.helpers import csv_rows

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ["+experiment=smoke", "total_frames=700", "progress=false"]


def environ(root: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    env.update(MEMRL_ROOT=str(root), PYTHONPATH=str(ROOT))
    return env


def start(args: list[str], root: Path) -> subprocess.Popen:
    def default_sigint() -> None:  # a background job of a shell would ignore SIGINT
        signal.signal(signal.SIGINT, signal.SIG_DFL)

    return subprocess.Popen([sys.executable, "-m", *args], cwd=ROOT, env=environ(root),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=default_sigint)


def run_folder(root: Path) -> Path:
    runs = list((root / "outputs" / "train" / "runs").glob("*"))
    assert len(runs) == 1, runs
    return runs[0]


def wait_for_episodes(root: Path, proc: subprocess.Popen, n: int, timeout: float = 240) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        assert proc.poll() is None, proc.communicate()
        found = list((root / "outputs" / "train" / "runs").glob("*/episodes.csv"))
        if found and len(found[0].read_text().splitlines()) > n:
            return
        time.sleep(0.2)
    raise AssertionError("no episodes")


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("full")
    proc = subprocess.run([sys.executable, "-m", "memrl.train", *SMOKE], cwd=ROOT,
                          env=environ(root), capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    return run_folder(root)


@pytest.mark.parametrize(("sig", "status"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_signal_during_training_keeps_a_checkpoint_and_prints_the_resume_command(
        tmp_path, uninterrupted, sig, status):
    stop_and_resume(tmp_path, SMOKE, uninterrupted, sig, status)


def test_signal_during_batched_training_stops_mid_episode_and_resumes_exactly(tmp_path):
    args = [*SMOKE, "env.num_envs=4"]
    full = tmp_path / "full"
    proc = subprocess.run([sys.executable, "-m", "memrl.train", *args], cwd=ROOT,
                          env=environ(full), capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    stop_and_resume(tmp_path / "cut", args, run_folder(full), signal.SIGTERM, 143)


def stop_and_resume(tmp_path: Path, args: list[str], uninterrupted: Path, sig: int, status: int) -> None:
    tmp_path.mkdir(exist_ok=True)
    proc = start(["memrl.train", *args], tmp_path)
    wait_for_episodes(tmp_path, proc, 5)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == status, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert "Traceback" not in err and "leaked semaphore" not in err, err
    last = lines[-1]
    assert last.startswith(f"interrupted by {signal.Signals(sig).name}: ") and "resume with: " in last
    run = run_folder(tmp_path)
    assert (run / "checkpoints" / "last" / "COMPLETE").is_file()
    assert not list(run.rglob("*.tmp")) and not (run / "checkpoints" / "final.pt").exists()

    command = shlex.split(last.split("resume with: ", 1)[1])
    assert command[:3] == ["python", "-m", "memrl.train"] and command[-1] == f"resume={run}"
    again = subprocess.run([sys.executable, *command[1:]], cwd=ROOT, env=environ(tmp_path),
                           capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr
    a = torch.load(uninterrupted / "checkpoints" / "final.pt", weights_only=False)["qnet"]
    b = torch.load(run / "checkpoints" / "final.pt", weights_only=False)["qnet"]
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert csv_rows(run / "episodes.csv") == csv_rows(uninterrupted / "episodes.csv")


@pytest.mark.parametrize("after_s", [4, 12], ids=["workers starting", "workers driving"])
def test_signal_during_evaluation_stops_its_workers_and_leaves_no_folder(tmp_path, after_s):
    # 2 x 5,000 episodes: far more than the 300 s below allow, so an evaluation whose workers
    # were not stopped (they drove every queued episode) fails here instead of passing late
    proc = start(["memrl.evaluate", "policy=scripted", "protocol.episodes=5000", "workers=2",
                  "progress=false"], tmp_path)
    time.sleep(after_s)
    assert proc.poll() is None, proc.communicate()
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 130, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert "Traceback" not in err and "leaked semaphore" not in err, err
    assert lines[-1].startswith("interrupted by SIGINT: nothing written; run again with: python -m "
                                "memrl.evaluate policy=scripted"), err
    runs = tmp_path / "outputs" / "evaluate" / "runs"
    assert not runs.exists() or list(runs.iterdir()) == []


def test_signal_during_a_study_keeps_its_runs_and_the_printed_command_finishes_it(tmp_path):
    from tests.test_study import study_overrides

    train = ["+experiment=smoke", "total_frames=900", "agent.warmup_frames=16", "buffer.capacity=400",
             "env.duration=30", "logger=none", "checkpoint_every=2", "eval.every=0"]
    folder = tmp_path / "s"
    args = [*study_overrides(folder, train, modes="[Default]", report=("rollouts.rows=[]",), seeds="[0]"),
            "study.baselines=[]", "study.jobs=1"]
    proc = start(["memrl.study", *args], tmp_path)
    run = folder / "runs" / "Default_constant_s0"
    end = time.monotonic() + 240
    while not ((run / "episodes.csv").is_file() and len((run / "episodes.csv").read_text().splitlines()) > 8):
        assert proc.poll() is None and time.monotonic() < end, proc.communicate()
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 143, err
    assert "Traceback" not in err and "leaked semaphore" not in err, err
    assert "Traceback" not in out and "failed" not in out, out  # a stop asked for is no failure
    log = (run / "train.log").read_text()
    assert "Traceback" not in log and "failed" not in log
    assert ": stopped by SIGTERM; its checkpoint is kept" in log
    last = [ln for ln in err.splitlines() if ln.strip()][-1]
    assert last.startswith("interrupted by SIGTERM: ") and "continue with: " in last, err
    assert (run / "checkpoints" / "last" / "COMPLETE").is_file() and not (run / "summary.json").exists()
    assert not list(folder.rglob("*.tmp"))
    command = shlex.split(last.split("continue with: ", 1)[1])
    again = subprocess.run([sys.executable, *command[1:]], cwd=ROOT, env=environ(tmp_path),
                           capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr[-3000:]
    assert (run / "summary.json").is_file() and (folder / "report.md").is_file()


def test_a_deferred_stop_waits_for_the_check_and_a_second_signal_stops_at_once():
    from memrl import stop

    stop.install()
    try:
        with pytest.raises(stop.Interrupted) as info:
            with stop.deferred():
                os.kill(os.getpid(), signal.SIGTERM)
                assert stop.stop_requested() == signal.SIGTERM  # only asked, not raised
                with pytest.raises(stop.Interrupted):  # a second signal: at once
                    os.kill(os.getpid(), signal.SIGINT)
        assert info.value.exit_status == 143  # the stop not acted on is raised on leaving
        assert stop.stop_requested() is None
    finally:
        stop.uninstall()


def test_a_signal_masked_by_library_clean_up_still_stops_training_as_a_signal(
        compose_cfg, tmp_path, demos, monkeypatch):
    # A second signal raises at once, wherever the loop is; inside DQNLoss, tensordict's
    # to_module context turns it into a RuntimeError on its way out (tensordict 0.11). train()
    # must still end as a stop (the study then stops instead of starting its next run).
    from memrl.modules.qnet import QNetwork
    from memrl.stop import Interrupted
    from memrl.train import train
    from tests.helpers import TINY

    forward, calls = QNetwork.forward, {"n": 0}

    def interrupted_forward(self, x):
        if torch.is_grad_enabled():  # the online forward inside DQNLoss (acting runs without)
            calls["n"] += 1
            if calls["n"] == 10:
                raise Interrupted(signal.SIGTERM)
        return forward(self, x)

    monkeypatch.setattr(QNetwork, "forward", interrupted_forward)
    with pytest.raises(Interrupted) as info:
        train(compose_cfg("train", TINY + ["total_episodes=6"]), tmp_path / "run", demos=demos)
    assert info.value.signum == signal.SIGTERM and calls["n"] == 10


def test_interruption_finds_the_signal_behind_other_errors():
    from memrl.stop import Interrupted, interruption

    stop = Interrupted(signal.SIGINT)
    try:
        try:
            raise stop
        except Interrupted:
            raise RuntimeError("clean-up failed") from None  # __context__ is kept
    except RuntimeError as err:
        masked = err
    assert interruption(masked) is stop
    assert interruption(RuntimeError("no signal")) is None
    assert interruption(ValueError("x")) is None


def test_a_stop_once_hydra_made_the_run_folder_removes_it_and_prints_the_command(tmp_path):
    """A signal after Hydra wrote ``.hydra/`` and ``train.log`` but before the task took over
    is a stop before the first checkpoint (docs/errors.md): the folder goes, the command is printed."""
    import signal as signal_module

    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import open_dict

    from memrl.cli import interrupted_before_task
    from memrl.configs import register_configs
    from memrl.stop import Interrupted
    from tests.conftest import CONF_DIR

    register_configs()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name="train", overrides=["seed=3"], return_hydra_config=True)
    run = tmp_path / "outputs" / "train" / "runs" / "now"
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "config.yaml").write_text("seed: 3\n")
    (run / "train.log").write_text("")
    with open_dict(cfg):
        cfg.hydra.runtime.output_dir = str(run)
    before = HydraConfig.instance().cfg
    HydraConfig.instance().set_config(cfg)
    try:
        line = interrupted_before_task(Interrupted(signal_module.SIGTERM))
    finally:
        HydraConfig.instance().cfg = before
    assert line == ("interrupted by SIGTERM before the first checkpoint: nothing to resume; "
                    "start again with: python -m memrl.train seed=3")
    assert not run.exists()


def test_the_go_on_command_of_a_stopped_evaluation_keeps_its_output_folder(tmp_path):
    """``resume_command`` keeps ``hydra.run.dir``: the re-run's log and ``.hydra/`` land in the
    same folder, not in a new ``outputs/evaluate/runs/<time>``."""
    import types

    from memrl.evaluation.session import resume_command
    from tests.helpers import inside_hydra_run

    out = tmp_path / "my eval"
    cand = types.SimpleNamespace(name="scripted", meta={"kind": "driver"})
    assert resume_command(cand, out) == f"python -m memrl.evaluate policy=scripted resume={out}"
    line = inside_hydra_run("evaluate", ["policy=scripted", f"hydra.run.dir={out}"],
                            lambda: resume_command(cand, out))
    assert line == f"python -m memrl.evaluate policy=scripted resume={out} 'hydra.run.dir={out}'"
