"""Every weights file memrl writes carries a SHA-256 of its content that every reader checks:
one flipped byte is refused naming the file; files from before checksums load with one
warning line."""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import pytest
import torch

from memrl.checkpoint import CheckpointError, load_qnet, load_stage1_qnet, save_qnet
from memrl.checkpoint.weights import CHECKSUM_KEY, load_weights, save_weights
from memrl.errors import is_user_error, one_line
from memrl.modules.qnet import QNetwork
from tests.helpers import TINY, flip_middle_byte, tiny, tree_hashes

ROOT = Path(__file__).resolve().parents[1]
SMALL = ["protocol.episodes=2", "protocol.duration=20", "workers=1", "batch=2", "progress=false"]


def damaged(line: str, file: Path) -> None:
    assert line == f"{file}: damaged weights file, its SHA-256 differs from the one written with " \
                   "it (restore it or train it again)", line


def test_a_changed_value_is_refused_and_the_same_payload_loads(tmp_path):
    payload = {"qnet": {"w": torch.arange(6.0).reshape(2, 3)}, "env": {"duration": 30}}
    file = save_weights(tmp_path / "w.pt", payload)
    loaded = load_weights(file)
    assert CHECKSUM_KEY not in loaded and torch.equal(loaded["qnet"]["w"], payload["qnet"]["w"])
    state = torch.load(file, weights_only=False)
    state["env"]["duration"] = 31  # a record changed, the weights as they were
    torch.save(state, file)
    with pytest.raises(CheckpointError) as info:
        load_weights(file)
    damaged(one_line(info.value), file)


def test_a_flipped_byte_in_final_pt_is_refused_by_evaluate(smoke_run, tmp_path, compose_cfg):
    from memrl.evaluate import evaluate

    run = tmp_path / "run"
    shutil.copytree(smoke_run, run)
    final = run / "checkpoints" / "final.pt"
    size = final.stat().st_size
    flip_middle_byte(final)
    assert final.stat().st_size == size
    before = tree_hashes(run)
    with pytest.raises(CheckpointError) as info:
        evaluate(compose_cfg("evaluate", [f"policy.run={run}", *SMALL]), tmp_path / "out")
    assert is_user_error(info.value)
    damaged(one_line(info.value), final)
    assert tree_hashes(run) == before and not (run / "eval").exists()


def test_a_flipped_byte_in_a_pool_network_is_refused_at_start(smoke_run, tmp_path, compose_cfg):
    from memrl.schemas import check_train

    final = tmp_path / "pool" / "final.pt"
    final.parent.mkdir()
    shutil.copy(smoke_run / "checkpoints" / "final.pt", final)
    flip_middle_byte(final)
    with pytest.raises(CheckpointError) as info:
        check_train(compose_cfg("train", [*TINY, "opponent=learned", f"env.opponent.pool=[{final}]"]))
    damaged(one_line(info.value), final)


@pytest.fixture
def flipped_b_run(smoke_b_run, tmp_path) -> Path:
    run = tmp_path / "b"
    shutil.copytree(smoke_b_run, run)
    flip_middle_byte(run / "checkpoints" / "stage1.pt")
    return run


def test_a_stage2_resume_with_a_flipped_byte_in_stage1_pt_is_refused(flipped_b_run, compose_cfg):
    from memrl.train import train

    before = tree_hashes(flipped_b_run)
    with pytest.raises(CheckpointError) as info:
        train(compose_cfg("train", [*tiny("B"), "total_episodes=3", f"resume={flipped_b_run}"]))
    damaged(one_line(info.value), flipped_b_run / "checkpoints" / "stage1.pt")
    assert tree_hashes(flipped_b_run) == before


def test_stage1_init_from_a_flipped_stage1_pt_is_refused(flipped_b_run, tmp_path, compose_cfg):
    from memrl.train import train

    before = tree_hashes(flipped_b_run)
    cfg = compose_cfg("train", [*tiny("B"), f"mode.stage1.init={flipped_b_run}"])
    with pytest.raises(ValueError) as info:
        train(cfg, tmp_path / "new")
    file = flipped_b_run / "checkpoints" / "stage1.pt"
    line = one_line(info.value)
    assert line.startswith("config 'mode.stage1.init': ")
    damaged(line.removeprefix("config 'mode.stage1.init': "), file)
    assert not (tmp_path / "new").exists() and tree_hashes(flipped_b_run) == before
    with pytest.raises(CheckpointError):  # the study's stage-1 evaluation reads it so too
        load_stage1_qnet(flipped_b_run)


def test_every_weights_file_memrl_writes_carries_its_checksum(smoke_b_run, tmp_path):
    for file in (smoke_b_run / "checkpoints" / "final.pt", smoke_b_run / "checkpoints" / "stage1.pt",
                 save_qnet(tmp_path / "pool" / "episode_0000010.pt", QNetwork(), {})):  # snapshots
        assert len(torch.load(file, weights_only=False)[CHECKSUM_KEY]) == 64
        load_weights(file)


def test_a_file_from_before_checksums_loads_with_one_warning_line(tmp_path, caplog, monkeypatch):
    import memrl.checkpoint.weights

    monkeypatch.setattr(memrl.checkpoint.weights, "_warned", set())
    file = tmp_path / "old" / "final.pt"
    file.parent.mkdir()
    torch.save({"qnet": QNetwork().state_dict(), "env": {}}, file)
    with caplog.at_level(logging.WARNING, logger="memrl.checkpoint.weights"):
        load_qnet(file)
        load_qnet(file)  # once per file
    lines = [r.getMessage() for r in caplog.records if r.name == "memrl.checkpoint.weights"]
    assert lines == [f"{file}: written before weights files carried a checksum; loaded unverified"]


def test_the_committed_results_still_load(caplog, monkeypatch):
    import memrl.checkpoint.weights

    monkeypatch.setattr(memrl.checkpoint.weights, "_warned", set())  # as in a fresh process
    run = ROOT / "docs" / "results" / "table3_300k" / "runs" / "B_constant_s4"
    with caplog.at_level(logging.WARNING, logger="memrl.checkpoint.weights"):
        assert isinstance(load_qnet(run)[0], torch.nn.Module)
        assert isinstance(load_stage1_qnet(run), torch.nn.Module)
    lines = [r.getMessage() for r in caplog.records if r.name == "memrl.checkpoint.weights"]
    assert [line.split(": ", 1)[0].rsplit("/", 1)[-1] for line in lines] == ["final.pt", "stage1.pt"]
