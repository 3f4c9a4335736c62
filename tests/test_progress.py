"""Progress bars draw only on a terminal; off one, the periodic log lines take their place."""

from __future__ import annotations

import io
import os
import re
import subprocess
import sys
from pathlib import Path

from memrl.progress import drawn, progress_bar
from tests.helpers import tiny

ROOT = Path(__file__).resolve().parents[1]
BAR = re.compile(r"\d+%\|")
"""A tqdm bar's redraw (``  40%|████  | 4/10 ...``)."""


class FakeTerminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_bar_is_drawn_only_on_a_terminal(monkeypatch):
    monkeypatch.setattr(sys, "stderr", io.StringIO())
    assert not drawn(True) and progress_bar(True, total=3).disable
    terminal = FakeTerminal()
    monkeypatch.setattr(sys, "stderr", terminal)
    assert drawn(True) and not drawn(False)
    bar = progress_bar(True, total=3, desc="x", file=terminal)
    bar.update(3)
    bar.close()
    assert BAR.search(terminal.getvalue())
    assert progress_bar(False, total=3).disable


def test_a_run_off_a_terminal_writes_log_lines_not_bar_redraws(tmp_path):
    """Mode B (records its prior knowledge, stage 1, stage 2) with ``progress=true`` and its
    output to pipes: no bar redraw anywhere; the periodic update lines in train.log instead."""
    args = [a for a in tiny("B") if not a.startswith("progress=")] + ["progress=true"]
    env = {**os.environ, "MEMRL_ROOT": str(tmp_path), "SDL_VIDEODRIVER": "dummy"}
    proc = subprocess.run([sys.executable, "-m", "memrl.train", *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = proc.stdout + proc.stderr
    assert "\r" not in out and not BAR.search(out)
    assert len(out.splitlines()) < 50
    (log,) = (tmp_path / "outputs" / "train" / "runs").glob("*/train.log")
    assert re.search(r"updates \d+, env steps \d+, stage B2: loss", log.read_text())
