"""A recording over several sittings, and a recording stopped or damaged: what is left, what is said."""

from __future__ import annotations

import errno
import fcntl
import os
import pty
import re
import signal
import struct
import subprocess
import sys
import termios
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from memrl.data.demos import load_demos, read_metadata
from memrl.record import record
from memrl.stop import Stopped

ROOT = Path(__file__).resolve().parents[1]
ENV = ["env.duration=30", "env.vehicles_count=[0,2]", "progress=false"]


def _tensors_equal(a, b) -> bool:
    return all(torch.equal(a[k], b[k]) for k in a.keys(include_nested=True, leaves_only=True))


def test_log_and_summary_count_the_same_saved_transitions(compose_cfg, tmp_path, capsys, caplog):
    out = tmp_path / "tail"
    cfg = compose_cfg("record", ["episodes=2", "tail_steps=5", "keep=all", f"out={out}", *ENV])
    with caplog.at_level("INFO"):
        summary = record(cfg)
    saved = load_demos(out).shape[0]
    assert summary.kept["transitions"] == saved < summary.kept["steps"]
    assert f"saved {saved} transitions" in caplog.text
    assert f"{saved} transitions saved (of their {summary.kept['steps']} steps)" in capsys.readouterr().out


def test_stale_temporary_folders_are_cleaned_by_the_next_recording(compose_cfg, tmp_path):
    out = tmp_path / "data"
    stale = tmp_path / ".data.tmp-deadbeef"  # what kill -9 during save_demos leaves
    (stale / "transitions").mkdir(parents=True)
    other = tmp_path / ".other.tmp-deadbeef"  # another dataset's: not ours to remove
    other.mkdir()
    record(compose_cfg("record", ["episodes=1", "keep=all", f"out={out}", *ENV]))
    assert not stale.exists() and other.exists() and (out / "metadata.json").is_file()


def test_full_disk_names_the_dataset_path(compose_cfg, tmp_path, monkeypatch):
    from memrl.errors import is_user_error, one_line

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")  # as numpy's zip writer raises it

    monkeypatch.setattr(np, "savez_compressed", full)
    out = tmp_path / "full"
    with pytest.raises(OSError) as err:
        record(compose_cfg("record", ["episodes=1", "keep=all", f"out={out}", *ENV]))
    assert is_user_error(err.value) and str(out) in one_line(err.value)
    assert not out.exists() and not list(tmp_path.glob(".full.tmp-*"))


def test_two_sittings_give_the_dataset_of_one(compose_cfg, tmp_path):
    one = tmp_path / "one"
    record(compose_cfg("record", ["episodes=3", "keep=all", f"out={one}", *ENV]))
    two = tmp_path / "two"
    from memrl.data import recording

    calls = {"n": 0}
    real = recording.to_transitions

    def stop_in_second(*args, **kwargs):  # the second episode ends in Ctrl-C
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    recording.to_transitions = stop_in_second
    try:
        with pytest.raises(Stopped, match=f"go on with: python -m memrl.record resume={two}") as stop:
            record(compose_cfg("record", ["episodes=3", "keep=all", f"out={two}", *ENV]))
    finally:
        recording.to_transitions = real
    assert stop.value.status == 130
    assert read_metadata(two)["sittings"]["next_episode"] == 1
    summary = record(compose_cfg("record", [f"resume={two}", "progress=false"]))
    assert summary.recorded["episodes"] == 3
    a, b = load_demos(one), load_demos(two)
    assert a.shape == b.shape and _tensors_equal(a, b)
    assert read_metadata(two)["counts"] == read_metadata(one)["counts"]
    with pytest.raises(Exception, match="is finished"):
        record(compose_cfg("record", [f"resume={two}", "progress=false"]))


@pytest.mark.parametrize(("sig", "status", "name"), [(signal.SIGINT, 130, "SIGINT"),
                                                     (signal.SIGTERM, 143, "SIGTERM")])
def test_signal_during_recording_stops_cleanly_and_resumes(compose_cfg, tmp_path, sig, status, name):
    out = tmp_path / "sig"
    cmd = [sys.executable, "-m", "memrl.record", "episodes=20", "keep=all", f"out={out}",
           "env.duration=30", "env.vehicles_count=[0,2]", "progress=true",
           f"hydra.run.dir={tmp_path / 'hydra'}"]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    terminal, its_end = pty.openpty()  # stderr a terminal, as at a keyboard: the bar is drawn there
    fcntl.ioctl(its_end, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 120, 0, 0))  # 24 x 120 (0 x 0: no bar)
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=its_end,
                            text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    os.close(its_end)
    err: list[str] = []

    def read() -> None:
        while True:
            try:
                chunk = os.read(terminal, 4096)
            except OSError:  # the child closed its end
                return
            if not chunk:
                return
            err.append(chunk.decode(errors="replace"))

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    deadline = time.time() + 120
    while not re.search(r"record:.* ([1-9]\d*)/20", "".join(err)):
        assert time.time() < deadline and proc.poll() is None, "".join(err)
        time.sleep(0.2)
    proc.send_signal(sig)
    assert proc.wait(60) == status
    reader.join(5)
    os.close(terminal)
    lines = [ln for ln in "".join(err).replace("\r", "\n").splitlines() if ln.strip() and "record:" not in ln]
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"interrupted ({name}) after episode ")
    assert lines[0].endswith(f"go on with: python -m memrl.record resume={out}")
    assert not list(tmp_path.glob(".sig.*")) and "Traceback" not in "".join(err)
    done = read_metadata(out)["sittings"]["next_episode"]
    assert 0 < done < 20
    # the printed command finishes it; the same as a recording never interrupted
    record(compose_cfg("record", [f"resume={out}", "episodes=20", "progress=false"]))
    whole = tmp_path / "whole"
    record(compose_cfg("record", ["episodes=20", "keep=all", f"out={whole}", *ENV]))
    assert _tensors_equal(load_demos(out), load_demos(whole))
