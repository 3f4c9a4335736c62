"""A stand-in trainer for the study's process-pool test: light to import in a spawned process
(no torch), it writes what a finished run holds, or fails for a run named ``*_s1``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


def fake_trainer(cfg: Any, run_dir: str, resume: bool) -> dict[str, Any]:
    path = Path(run_dir)
    if path.name.endswith("_s1"):
        raise RuntimeError(f"{path.name} diverged")
    (path / "checkpoints").mkdir(parents=True, exist_ok=True)
    (path / "checkpoints" / "final.pt").write_bytes(b"")
    summary = {"run_dir": run_dir, "resume": resume}
    (path / "summary.json").write_text(json.dumps(summary))
    return summary


def fake_group_trainer(cfgs: Any, run_dirs: list[str], resumes: list[bool]) -> list[dict[str, Any]]:
    """:func:`fake_trainer` for each run in turn, in one process (its id in each summary): a
    ``*_s1`` run fails the group after the runs before it finished."""
    import os

    out = []
    for cfg, run_dir, resume in zip(cfgs, run_dirs, resumes, strict=True):
        out.append(fake_trainer(cfg, run_dir, resume))
        summary = {**out[-1], "pid": os.getpid()}
        (Path(run_dir) / "summary.json").write_text(json.dumps(summary))
    return out
