"""A damaged checkpoint is refused naming the damaged file; every run records its provenance."""

from __future__ import annotations

import json
import platform
import shutil
import subprocess

import pytest

from memrl.checkpoint import resume as ckpt
from memrl.dqn.learner import native_bf16
from memrl.errors import is_user_error, one_line
from memrl.provenance import PROVENANCE_FILE, auto_precision_change, cpu_model
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
    assert entry["machine"]["cpu_model"] == cpu_model()
    assert entry["machine"]["native_bf16"] is native_bf16()  # what agent.precision=auto trained in
    assert entry["time"].endswith("+00:00")


def test_cpu_model_is_read_from_cpuinfo(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nvendor_id\t: GenuineIntel\nmodel name\t: Intel(R) Xeon(R) Processor\n")
    assert cpu_model(info) == "Intel(R) Xeon(R) Processor"
    assert cpu_model(tmp_path / "absent") == (platform.processor() or platform.machine())


def test_a_resume_on_a_cpu_with_other_native_bf16_is_logged(compose_cfg, finished_run, tmp_path, caplog):
    """precision=auto follows the CPU: a run carried to a machine that differs says so once."""
    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    entries = json.loads((run / PROVENANCE_FILE).read_text())
    entries[0]["machine"].update(native_bf16=not native_bf16(), cpu_model="elsewhere")
    (run / PROVENANCE_FILE).write_text(json.dumps(entries))
    with caplog.at_level("WARNING", logger="memrl.train"):
        train(compose_cfg("train", TINY + ["total_episodes=3", f"resume={run}"]))
    was, now = ("bfloat16", "float32") if not native_bf16() else ("float32", "bfloat16")
    [line] = [r.getMessage() for r in caplog.records if "agent.precision=auto" in r.getMessage()]
    assert line.startswith(f"agent.precision=auto: this run started with its conv trunk in {was} (elsewhere)")
    assert f"goes on in {now} on this CPU ({cpu_model()})" in line
    assert [e["event"] for e in json.loads((run / PROVENANCE_FILE).read_text())] == ["start", "resume"]
    entries[0]["machine"]["native_bf16"] = native_bf16()  # the same CPU kind: nothing to say
    assert auto_precision_change([entries[0], entries[0]]) is None
    assert auto_precision_change([entries[0]]) is None
    del entries[0]["machine"]["native_bf16"]  # written before the key: nothing to compare
    assert auto_precision_change([entries[0], {"machine": {"native_bf16": True}}]) is None
