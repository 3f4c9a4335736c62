"""A damaged checkpoint is refused naming the damaged file; every run records its provenance."""

from __future__ import annotations

import json
import shutil
import subprocess

import pytest

from memrl.dqn import checkpoint as ckpt
from memrl.errors import is_user_error, one_line
from memrl.provenance import PROVENANCE_FILE
from memrl.train import train
from tests.helpers import TINY


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """A 2-episode run whose last checkpoint holds an agent buffer."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from memrl.configs import register_configs
    from tests.conftest import CONF_DIR

    register_configs()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("train", TINY + ["total_episodes=2"])
    run = tmp_path_factory.mktemp("run")
    train(cfg, run)
    return run


def truncate(path, size):
    with path.open("r+b") as f:
        f.truncate(size)


def flip_a_byte(path):
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))


DAMAGES = [
    ("buffer/storage/action.memmap", lambda p: truncate(p, 8), "bytes where"),
    ("buffer/storage/action.memmap", flip_a_byte, "CRC-32"),
    ("buffer/storage/frame_ring.npy", lambda p: truncate(p, p.stat().st_size // 2), "bytes where"),
    ("buffer/storage/next/reward.memmap", lambda p: p.unlink(), "missing"),
    ("state.pt", lambda p: truncate(p, 100), "bytes where"),
]


@pytest.mark.parametrize(("name", "damage", "why"), DAMAGES,
                         ids=[f"{n}:{w}" for n, _, w in DAMAGES])
def test_resume_refuses_a_damaged_checkpoint_naming_the_file(compose_cfg, finished_run, tmp_path,
                                                             name, damage, why):
    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    target = run / "checkpoints" / "last" / name
    damage(target)
    before = {p: p.stat().st_mtime_ns for p in run.rglob("*") if p.is_file()}
    cfg = compose_cfg("train", TINY + ["total_episodes=3", f"resume={run}"])
    with pytest.raises(ckpt.CheckpointError) as info:
        train(cfg)
    message = one_line(info.value)
    assert is_user_error(info.value) and "\n" not in message
    assert message.startswith(str(target)) and why in message
    # nothing was written into the run folder: the CSVs were not rewound, no provenance added
    assert {p: p.stat().st_mtime_ns for p in run.rglob("*") if p.is_file()} == before


def test_a_checkpoint_without_its_manifest_is_refused_naming_it(compose_cfg, finished_run, tmp_path):
    """Nothing verifies a checkpoint whose manifest is gone: refused, not trusted."""
    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    last = run / "checkpoints" / "last"
    (last / ckpt.MANIFEST).unlink()
    ring = last / "buffer" / "storage" / "frame_ring.npy"
    truncate(ring, ring.stat().st_size // 2)
    with pytest.raises(ckpt.CheckpointError) as info:
        train(compose_cfg("train", TINY + ["total_episodes=3", f"resume={run}"]))
    assert one_line(info.value).startswith(str(last / ckpt.MANIFEST))


def test_an_intact_checkpoint_passes_its_manifest(finished_run):
    last = finished_run / "checkpoints" / "last"
    files = json.loads((last / ckpt.MANIFEST).read_text())["files"]
    assert "state.pt" in files and "buffer/storage/action.memmap" in files
    assert "buffer/storage/frame_ring.npy" in files
    ckpt.check_manifest(last)


def test_a_run_records_its_provenance(finished_run):
    entries = json.loads((finished_run / PROVENANCE_FILE).read_text())
    assert [e["event"] for e in entries] == ["start"]
    entry = entries[0]
    head = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                          cwd=ckpt.__file__.rsplit("/memrl/", 1)[0])
    if head.returncode == 0:
        assert entry["git"]["commit"] == head.stdout.strip()
        assert isinstance(entry["git"]["dirty"], bool)
    for name in ("torch", "torchrl", "tensordict", "hydra-core", "gymnasium", "highway-env"):
        assert entry["versions"][name], name
    assert entry["machine"]["cpu_count"] >= 1 and entry["machine"]["platform"]
    assert entry["time"].endswith("+00:00")
