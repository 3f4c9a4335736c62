"""The user's exact command lines, run as subprocesses into a temporary project root."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from tests.helpers import TINY

ROOT = Path(__file__).resolve().parents[1]
SMALL = [o for o in TINY if o != "+experiment=smoke"] + ["total_episodes=2"]


def run(args: list[str], root: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "MEMRL_ROOT": str(root), "SDL_VIDEODRIVER": "dummy"}
    return subprocess.run([sys.executable, "-m", "memrl.train", *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=900)


def job_dirs(root: Path) -> list[Path]:
    sweeps = sorted((root / "outputs" / "train" / "multiruns").iterdir())
    assert len(sweeps) == 1
    return sorted(p for p in sweeps[0].iterdir() if p.is_dir() and p.name.isdigit())


def test_verbatim_mode_b_three_seed_multirun(tmp_path):
    proc = run(["+mode=B", "-m", "seed=0,1,2", "+experiment=smoke", *SMALL], tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    jobs = job_dirs(tmp_path)
    assert len(jobs) == 3
    seeds = sorted(json.loads((j / "summary.json").read_text())["seed"] for j in jobs)
    assert seeds == [0, 1, 2]
    assert all(json.loads((j / "summary.json").read_text())["stage"] == "B2" for j in jobs)
    assert not (ROOT / "multirun").exists() and not (tmp_path / "multirun").exists()


def test_a_bad_config_in_any_job_stops_the_sweep_before_it_starts(tmp_path):
    proc = run(["-m", "seed=0,1", "agent.lr=0.001,-1.0", *SMALL], tmp_path)
    assert proc.returncode == 2, proc.stderr[-3000:]
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: job 1 [seed=0 agent.lr=-1.0"), proc.stderr
    assert "'agent.lr'" in lines[0]
    assert not (tmp_path / "outputs").exists()  # no job launched, no sweep folder


def test_failing_jobs_let_the_others_finish_then_the_sweep_exits_non_zero(tmp_path):
    """A failure found only while a job runs (here: a folder that is no dataset)."""
    empty = tmp_path / "not_a_dataset"
    empty.mkdir()
    data = tmp_path / "demos"
    env = {**os.environ, "MEMRL_ROOT": str(tmp_path)}
    rec = subprocess.run([sys.executable, "-m", "memrl.record", "episodes=2", "keep=all",
                          "env.duration=30", f"out={data}", "progress=false"], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=300)
    assert rec.returncode == 0, rec.stderr[-3000:]
    proc = run(["-m", "+mode=A", f"mode.demos_path={data},{empty}", "seed=0,1", *SMALL], tmp_path)
    assert proc.returncode == 1, proc.stderr[-3000:]
    jobs = job_dirs(tmp_path)
    assert len(jobs) == 4
    failed = [j for j in jobs if (j / "error.txt").exists()]
    assert [j.name for j in failed] == ["2", "3"]  # demos_path is the outer loop: jobs 2 and 3
    assert all((j / "summary.json").exists() for j in jobs if j not in failed)
    assert all(str(empty) in (j / "error.txt").read_text() for j in failed)
    report = proc.stderr[proc.stderr.index("sweep: "):].splitlines()
    assert report[0].startswith("sweep: 2 of 4 jobs failed")
    for line, job in zip(report[1:3], failed, strict=True):
        assert f"job {job.name} [" in line and f"mode.demos_path={empty}" in line
        assert line.endswith(str(job / "error.txt"))


def test_a_sweep_without_failures_exits_zero_and_reports_nothing(tmp_path):
    from memrl.hydra_callbacks import failure_report

    for num in ("0", "1", ".submitit"):
        (tmp_path / num).mkdir()
    assert failure_report(tmp_path) is None
    (tmp_path / "1" / "error.txt").write_text("Traceback ...\nValueError: boom\n")
    assert failure_report(tmp_path).splitlines() == [
        f"sweep: 1 of 2 jobs failed ({tmp_path}):",
        f"  job 1 []: ValueError: boom -> {tmp_path / '1' / 'error.txt'}"]


def test_joblib_launcher_runs_jobs_in_parallel_processes(tmp_path):
    proc = run(["-m", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", "seed=0,1", *SMALL],
               tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    jobs = job_dirs(tmp_path)
    assert len(jobs) == 2 and all((j / "summary.json").exists() for j in jobs)


def test_mode_by_opponent_grid_makes_eight_runs(tmp_path):
    import torch

    from memrl.checkpoint import save_qnet
    from memrl.modules.qnet import QNetwork

    torch.manual_seed(0)
    pool = save_qnet(tmp_path / "past" / "final.pt", QNetwork(), {})
    proc = run(["-m", "+mode=A,B", "opponent=constant,mixed", "seed=0,1", "+experiment=smoke",
                f"env.opponent.pool=[{pool}]", *SMALL], tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    jobs = job_dirs(tmp_path)
    assert len(jobs) == 8 and not any((j / "error.txt").exists() for j in jobs)
    import yaml

    grid = sorted((c["mode"]["name"], c["env"]["opponent"]["type"], c["seed"]) for c in
                  (yaml.safe_load((j / "config.yaml").read_text()) for j in jobs))
    assert grid == sorted((m, o, s) for m in "AB" for o in ("constant", "mixed") for s in (0, 1))


def test_submitit_local_launcher_runs_a_two_job_sweep(tmp_path):
    """Hydra's submitit launcher for real, with submitit's local executor (each job its own
    process, as on a Slurm node)."""
    proc = run(["-m", "hydra/launcher=submitit_local", "hydra.launcher.timeout_min=10",
                "seed=0,1", *SMALL], tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    jobs = job_dirs(tmp_path)
    assert [j.name for j in jobs] == ["0", "1"]
    assert sorted(json.loads((j / "summary.json").read_text())["seed"] for j in jobs) == [0, 1]
    assert all(json.loads((j / "summary.json").read_text())["episodes"] == 2 for j in jobs)
    assert len(list((jobs[0].parent / ".submitit").glob("*/*_0_log.out"))) == 2  # 2 submitit jobs


def test_slurm_launcher_config_asks_for_one_run_per_job():
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from memrl.configs import register_configs

    register_configs()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("train", ["hydra/launcher=slurm", "hydra.launcher.gpus_per_node=1"],
                      return_hydra_config=True)
    launcher = cfg.hydra.launcher
    assert launcher._target_.endswith("submitit_launcher.SlurmLauncher")
    assert (launcher.nodes, launcher.tasks_per_node, launcher.cpus_per_task) == (1, 1, 2)
    assert (launcher.gpus_per_node, launcher.mem_gb, launcher.timeout_min) == (1, 16, 1440)
