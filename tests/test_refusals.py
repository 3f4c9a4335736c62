"""Refused starts and resumes write nothing, and every file memrl reads is refused by name:
one ``error:`` line, exit status 2, the folders as they were."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from memrl.checkpoint import resume as ckpt
from memrl.errors import USAGE_EXIT, is_user_error, one_line
from tests.helpers import TINY, tiny

ROOT = Path(__file__).resolve().parents[1]


def cli(args: list[str], root: Path, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    env.update(MEMRL_ROOT=str(root), PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=300)


def snapshot(folder: Path) -> dict[str, int]:
    return {str(p.relative_to(folder)): p.stat().st_mtime_ns if p.is_file() else 0
            for p in folder.rglob("*")}


def refused(proc: subprocess.CompletedProcess, name: str) -> str:
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == USAGE_EXIT, proc.stderr
    assert len(lines) == 1 and lines[0].startswith("error: ") and name in lines[0], proc.stderr
    return lines[0]


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("finished")
    proc = cli(["memrl.train", *TINY, "total_episodes=2", f"hydra.run.dir={root / 'run'}"], root)
    assert proc.returncode == 0, proc.stderr
    return root / "run"


def truncate(path: Path, size: int) -> None:
    with path.open("r+b") as f:
        f.truncate(size)


DAMAGES = {
    "seed=1": (["seed=1"], None, "seed"),
    "env.num_envs=2": (["env.num_envs=2"], None, "num_envs"),
    "+mode=A": (["+mode=A"], None, "mode"),
    "damaged state.pt": ([], lambda last: truncate(last / "state.pt", 100), "state.pt"),
    "missing COMPLETE": ([], lambda last: (last / "COMPLETE").unlink(), "no complete checkpoint"),
    "garbled manifest": ([], lambda last: (last / ckpt.MANIFEST).write_text("{nope"), ckpt.MANIFEST),
    "deleted manifest": ([], lambda last: (last / ckpt.MANIFEST).unlink(), ckpt.MANIFEST),
    "garbled config.yaml": ([], lambda last: (last.parent.parent / "config.yaml").write_text(
        "a: [b\n"), "config.yaml"),
}


@pytest.mark.parametrize("case", list(DAMAGES))
def test_a_refused_resume_writes_nothing_into_the_run(finished_run, tmp_path, case):
    extra, damage, name = DAMAGES[case]
    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    if damage is not None:
        damage(run / "checkpoints" / "last")
    before = snapshot(run)
    proc = cli(["memrl.train", *TINY, "total_episodes=3", f"resume={run}", *extra], tmp_path)
    refused(proc, name)
    assert snapshot(run) == before  # no .hydra/resume_<time>/, no log lines, no rewound CSVs


def test_resume_of_a_folder_that_is_no_run_writes_nothing(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    refused(cli(["memrl.train", *TINY, f"resume={empty}"], tmp_path), "resume")
    assert list(empty.iterdir()) == []
    work = tmp_path / "checkout"  # resume=. from a checkout
    work.mkdir()
    (work / "notes.txt").write_text("mine\n")
    refused(cli(["memrl.train", *TINY, "resume=."], tmp_path, cwd=work), "resume")
    assert [p.name for p in work.iterdir()] == ["notes.txt"]


def test_a_checkpoint_without_its_manifest_is_refused_even_with_a_changed_byte(finished_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    last = run / "checkpoints" / "last"
    (last / ckpt.MANIFEST).unlink()
    action = last / "buffer" / "storage" / "action.memmap"
    data = bytearray(action.read_bytes())
    data[0] ^= 0x7F
    action.write_bytes(bytes(data))
    with pytest.raises(ckpt.CheckpointError) as info:
        ckpt.load_state(last)
    assert is_user_error(info.value) and one_line(info.value).startswith(str(last / ckpt.MANIFEST))


def test_stage1_init_from_a_truncated_stage1_pt_is_refused_naming_it(tmp_path):
    import torch

    source = tmp_path / "b_run" / "checkpoints" / "stage1.pt"
    source.parent.mkdir(parents=True)
    torch.save({"loss_module": {"w": torch.zeros(1000)}, "stage1": {}}, source)
    truncate(source, source.stat().st_size // 2)
    proc = cli(["memrl.train", *tiny("B"), f"mode.stage1.init={tmp_path / 'b_run'}"], tmp_path)
    refused(proc, str(source))
    assert not (tmp_path / "outputs" / "train" / "runs").exists() or \
        list((tmp_path / "outputs" / "train" / "runs").iterdir()) == []


@pytest.mark.parametrize("damage", ["truncated", "deleted"])
def test_a_stage2_resume_without_a_sound_stage1_pt_is_refused(compose_cfg, tmp_path, demos, damage):
    from memrl.train import train

    run = tmp_path / "b"
    train(compose_cfg("train", tiny("B") + ["total_episodes=2"]), run, demos=demos)
    stage1 = run / "checkpoints" / "stage1.pt"
    assert stage1.is_file()
    if damage == "deleted":
        stage1.unlink()
    else:
        truncate(stage1, 50)
    before = snapshot(run)
    with pytest.raises(ckpt.CheckpointError) as info:
        train(compose_cfg("train", tiny("B") + ["total_episodes=3", f"resume={run}"]), demos=demos)
    assert one_line(info.value).startswith(str(stage1))
    assert snapshot(run) == before


def test_evaluate_a_run_with_a_garbled_config_names_the_file(finished_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    (run / "config.yaml").write_text("mode: {name: [B\n")
    proc = cli(["memrl.evaluate", f"policy.run={run}", "protocol.episodes=1"], tmp_path)
    refused(proc, str(run / "config.yaml"))
    assert not (tmp_path / "outputs" / "evaluate" / "runs").exists() or \
        list((tmp_path / "outputs" / "evaluate" / "runs").iterdir()) == []


def test_learned_opponents_with_a_pool_that_matches_nothing(tmp_path):
    proc = cli(["memrl.train", *TINY, "opponent=learned", f"env.opponent.pool=[{tmp_path}/none/*.pt]"],
               tmp_path)
    refused(proc, "opponent.pool")
    assert not (tmp_path / "outputs").exists() or not list((tmp_path / "outputs").rglob("*.yaml"))


def test_report_of_a_folder_without_evaluation_names_it(tmp_path):
    folder = tmp_path / "not_evaluated"
    folder.mkdir()
    proc = cli(["memrl.report", f"runs=[{folder}]", "evaluate_missing=false"], tmp_path)
    refused(proc, str(folder))
    proc = cli(["memrl.report", f"runs=[{folder}]"], tmp_path)
    refused(proc, str(folder))
    assert not (tmp_path / "outputs" / "report" / "runs").exists() or \
        list((tmp_path / "outputs" / "report" / "runs").iterdir()) == []


def test_a_multirun_checks_every_job_before_launching_any(tmp_path):
    proc = cli(["memrl.train", "-m", "seed=0,1", "agent.lr=0", *TINY], tmp_path)
    line = refused(proc, "'agent.lr'")
    assert "job 0 [seed=0 agent.lr=0" in line
    proc = cli(["memrl.train", "-m", "seed=0,1", "total_episodes=1,0", *TINY[:2], *TINY[3:]], tmp_path)
    line = refused(proc, "'total_episodes'")
    assert "job 1 [seed=0 total_episodes=0" in line  # the first bad job, by its overrides
    assert not (tmp_path / "outputs").exists()


def test_a_study_called_with_changed_train_overrides_writes_nothing(tmp_path, compose_cfg):
    from memrl.study import check_record
    from tests.test_study import TRAIN, study_overrides

    folder = tmp_path / "s"
    check_record(folder, compose_cfg("study", study_overrides(folder)))
    (folder / "study.log").write_text("earlier lines\n")
    before = snapshot(folder)
    proc = cli(["memrl.study", *study_overrides(folder, [*TRAIN, "agent.lr=0.001"])], tmp_path)
    refused(proc, "study.train_overrides")
    assert snapshot(folder) == before and (folder / "study.log").read_text() == "earlier lines\n"
