"""A run evaluated without its ``config.yaml`` keeps its row and seed: they come from what the
run wrote (its checkpoint, its ``final.pt``), or the run is refused in one line."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch

from memrl.checkpoint import save_qnet
from memrl.errors import is_user_error, one_line
from memrl.evaluation.policies import CheckpointSource
from memrl.modules.qnet import QNetwork
from tests.helpers import tree_hashes

SMALL = ["protocol.episodes=2", "protocol.duration=20", "workers=1", "batch=2", "progress=false"]


@pytest.fixture
def b_run(smoke_b_run, tmp_path) -> Path:
    run = tmp_path / "b"
    shutil.copytree(smoke_b_run, run)
    (run / "config.yaml").unlink()
    return run


def test_a_mode_b_run_without_config_yaml_is_evaluated_as_b(b_run, compose_cfg, tmp_path):
    from memrl.evaluate import evaluate

    [result] = evaluate(compose_cfg("evaluate", [f"policy.run={b_run}", *SMALL]), tmp_path / "out")
    doc = json.loads((b_run / "eval" / "eval.json").read_text())
    assert (result.name, result.unit) == ("B", "seed 0")
    meta = doc["meta"]
    assert (doc["name"], doc["unit"], meta["mode"], meta["train_seed"]) == ("B", "seed 0", "B", 0)


def test_without_its_checkpoint_the_final_networks_record_names_the_row(b_run):
    shutil.rmtree(b_run / "checkpoints" / "last")
    [cand] = CheckpointSource(str(b_run)).candidates()
    assert (cand.name, cand.meta["unit"], cand.meta["mode"]) == ("B", "seed 0", "B")
    assert cand.env == torch.load(b_run / "checkpoints" / "final.pt", weights_only=False)["env"]


def test_a_run_that_recorded_neither_is_refused_naming_config_yaml(b_run, compose_cfg, tmp_path):
    from memrl.evaluate import evaluate

    shutil.rmtree(b_run / "checkpoints" / "last")
    (b_run / "summary.json").unlink()
    save_qnet(b_run / "checkpoints" / "final.pt", QNetwork(), {})  # weights without records
    before = tree_hashes(b_run)
    with pytest.raises(Exception) as info:
        evaluate(compose_cfg("evaluate", [f"policy.run={b_run}", *SMALL]), tmp_path / "out")
    line = one_line(info.value)
    assert is_user_error(info.value) and line.startswith(f"{b_run / 'config.yaml'}: missing, and ")
    assert "\n" not in line and tree_hashes(b_run) == before
