"""Pool workers end with the process that started them (``memrl.workers.die_with_parent``)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PARENT = """
import sys, time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from memrl.workers import die_with_parent

def task():
    import os, time
    print(os.getpid(), flush=True)
    time.sleep(600)  # a study's training run: far longer than the test waits

if __name__ == "__main__":
    init = die_with_parent if sys.argv[1] == "on" else None
    pool = ProcessPoolExecutor(1, mp_context=get_context("spawn"), initializer=init)
    pool.submit(task)
    time.sleep(600)
"""


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"  # a zombie has ended


def _worker_after_parent_killed(tmp_path: Path, initializer: str) -> bool:
    """Start a pool whose worker sleeps in its task, SIGKILL the parent, and say whether the
    worker still runs 5 s later (it ends at once when it gets the signal)."""
    script = tmp_path / "parent.py"
    script.write_text(PARENT)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    parent = subprocess.Popen([sys.executable, str(script), initializer], stdout=subprocess.PIPE,
                              text=True, env=env)
    worker = None
    try:
        assert parent.stdout is not None
        worker = int(parent.stdout.readline())
        parent.send_signal(signal.SIGKILL)
        parent.wait()
        for _ in range(50):
            if not _alive(worker):
                return False
            time.sleep(0.1)
        return True
    finally:
        parent.kill()
        if worker is not None and _alive(worker):
            os.kill(worker, signal.SIGKILL)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_pool_worker_ends_when_its_parent_is_killed(tmp_path):
    assert not _worker_after_parent_killed(tmp_path, "on")
    assert _worker_after_parent_killed(tmp_path, "off")  # what happens without it
