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


def cpu_model(cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """The CPU's model name (Linux ``/proc/cpuinfo``; elsewhere ``platform.processor()``)."""
    try:
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name") and ":" in line:
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine() -> dict[str, Any]:
    """The host: OS, CPU (model and whether it runs bf16 natively, which decides what
    ``agent.precision=auto`` trains in), core count, Python, and the GPU torch sees if it is loaded."""
    info: dict[str, Any] = {"hostname": platform.node(), "platform": platform.platform(),
                            "processor": platform.processor() or platform.machine(),
                            "cpu_model": cpu_model(),
                            "cpu_count": os.cpu_count(), "python": platform.python_version()}
    import sys

    torch = sys.modules.get("torch")  # not imported for this: recorded when the run has it
    if torch is not None:
        info["cuda"] = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
        from memrl.dqn.learner import native_bf16

        info["native_bf16"] = native_bf16()
    return info


def provenance(root: Path = PROJECT_ROOT) -> dict[str, Any]:
    """Everything above, with the time (UTC)."""
    return {"time": datetime.now(UTC).isoformat(timespec="seconds"), "git": git_state(root),
            "versions": versions(), "machine": machine()}


def auto_precision_change(entries: list[dict[str, Any]]) -> str | None:
    """Why a resumed run's ``agent.precision=auto`` now trains in another dtype than at its
    start (the start's CPU ran bf16 natively and this one does not, or the reverse); None
    when both agree or either did not record it (files written before ``native_bf16``)."""
    if len(entries) < 2:
        return None
    first, now = (e.get("machine", {}) for e in (entries[0], entries[-1]))
    was, is_ = first.get("native_bf16"), now.get("native_bf16")
    if was is None or is_ is None or was == is_:
        return None
    dtype = {True: "bfloat16", False: "float32"}
    return (f"agent.precision=auto: this run started with its conv trunk in {dtype[was]} "
            f"({first.get('cpu_model', '?')}) and goes on in {dtype[is_]} on this CPU "
            f"({now.get('cpu_model', '?')}); the updates from here on differ in precision")


def record_provenance(run_dir: Path, event: str = "start") -> dict[str, Any]:
    """Append this process's provenance (``event``: start or resume) to the run's file."""
    file = run_dir / PROVENANCE_FILE
    entries = read_provenance(run_dir)
    entry = {"event": event, **provenance()}
    file.write_text(json.dumps([*entries, entry], indent=2))
    return entry


def read_provenance(run_dir: Path) -> list[dict[str, Any]]:
    """The run's provenance entries, oldest first ([] without the file)."""
    file = run_dir / PROVENANCE_FILE
    return json.loads(file.read_text()) if file.is_file() else []
