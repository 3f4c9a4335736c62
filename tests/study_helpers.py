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
