"""What a run was made with: code version, library versions and machine (``provenance.json``)."""

from __future__ import annotations

import json
import os
import platform
import subprocess
from datetime import UTC, datetime
from importlib import metadata
from pathlib import Path
from typing import Any

PACKAGES = ("memrl", "torch", "torchrl", "tensordict", "hydra-core", "gymnasium", "highway-env",
            "numpy")
"""Distributions whose installed versions are recorded."""

PROVENANCE_FILE = "provenance.json"

PROJECT_ROOT = Path(__file__).resolve().parents[1]


def git_state(root: Path = PROJECT_ROOT) -> dict[str, Any]:
    """Commit of the checkout and whether it had uncommitted changes (None outside git)."""
    def git(*args: str) -> str | None:
        try:
            out = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True,
                                 timeout=10, check=True)
        except (OSError, subprocess.SubprocessError):
            return None
        return out.stdout.strip()

    commit = git("rev-parse", "HEAD")
    status = git("status", "--porcelain", "--untracked-files=no") if commit else None
    return {"commit": commit, "dirty": None if status is None else bool(status)}


def versions(packages: tuple[str, ...] = PACKAGES) -> dict[str, str | None]:
    """Installed version of each distribution (None: not installed)."""
    out: dict[str, str | None] = {}
    for name in packages:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def machine() -> dict[str, Any]:
    """The host: OS, CPU, core count, Python, and the GPU torch sees if it is loaded."""
    info: dict[str, Any] = {"hostname": platform.node(), "platform": platform.platform(),
                            "processor": platform.processor() or platform.machine(),
                            "cpu_count": os.cpu_count(), "python": platform.python_version()}
    import sys

    torch = sys.modules.get("torch")  # not imported for this: recorded when the run has it
    if torch is not None:
        info["cuda"] = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return info


def provenance(root: Path = PROJECT_ROOT) -> dict[str, Any]:
    """Everything above, with the time (UTC)."""
    return {"time": datetime.now(UTC).isoformat(timespec="seconds"), "git": git_state(root),
            "versions": versions(), "machine": machine()}


def record_provenance(run_dir: Path, event: str = "start") -> dict[str, Any]:
    """Append this process's provenance (``event``: start or resume) to the run's file."""
    file = run_dir / PROVENANCE_FILE
    entries = json.loads(file.read_text()) if file.is_file() else []
    entry = {"event": event, **provenance()}
    file.write_text(json.dumps([*entries, entry], indent=2))
    return entry
