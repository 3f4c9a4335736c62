"""Checkpoints: atomic save of everything a run needs to continue exactly, and safe loading."""

from __future__ import annotations

import random
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

RUNTIME_KEYS = ("resume", "paths", "logger", "progress", "total_frames", "total_episodes",
                "checkpoint_every", "log_every", "hydra")
"""Config keys that may differ between a run and its resumption (outputs and budgets)."""


LEGACY_VALUES: dict[str, Any] = {
    "agent": {"precision": "float32", "overlap": False},
    "env": {"bev": {"path_length": 0.0}, "initial_offset": 0.0, "initial_heading": 0.0,
            "initial_curvature": 0.0},
    "mode": {"stage1": {"lr": None, "drive_episodes": 0, "drive_seed": 0, "drive_target": 0.9,
                        "keep_best": True}},
}
"""Keys added to the config after checkpoints were first written, at the value that does what
the versions before them did: a checkpoint without a key is compared as if it held this
value, so resuming it asks for exactly that value (``agent.overlap=false`` ...)."""


def with_legacy_values(config: dict[str, Any], legacy: dict[str, Any] = LEGACY_VALUES,
                       ) -> dict[str, Any]:
    """``config`` with the keys of ``legacy`` that it lacks filled in (nested)."""
    out = dict(config)
    for key, value in legacy.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = with_legacy_values(out[key], value)
        elif key not in out and not isinstance(value, dict):
            out[key] = value
    return out


class CheckpointError(ValueError):
    """A checkpoint is missing, corrupt or from another config."""


def rng_state() -> dict[str, Any]:
    return {"torch": torch.get_rng_state(), "numpy": np.random.get_state(),
            "python": random.getstate()}


def set_rng_state(state: dict[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])


def comparable(cfg: DictConfig) -> dict[str, Any]:
    """The part of a config that must match for a checkpoint to be resumed."""
    data = OmegaConf.to_container(cfg, resolve=False)
    assert isinstance(data, dict)
    return {str(k): v for k, v in data.items() if k not in RUNTIME_KEYS}


def config_diff(a: dict[str, Any], b: dict[str, Any], prefix: str = "") -> list[str]:
    """Dotted keys whose values differ between two nested dicts."""
    out = []
    for key in sorted(set(a) | set(b)):
        va, vb = a.get(key, "<missing>"), b.get(key, "<missing>")
        if isinstance(va, dict) and isinstance(vb, dict):
            out += config_diff(va, vb, f"{prefix}{key}.")
        elif va != vb:
            out.append(f"{prefix}{key}: {va!r} (checkpoint) vs {vb!r} (now)")
    return out


def save(ckpt_dir: Path, state: dict[str, Any], buffer: Any | None) -> None:
    """Write ``state.pt`` and the buffer into a temporary folder, then swap it in atomically."""
    tmp = ckpt_dir.with_name(ckpt_dir.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    torch.save(state, tmp / "state.pt")
    if buffer is not None:
        buffer.dumps(tmp / "buffer")
    (tmp / "COMPLETE").write_text("ok\n")
    old = ckpt_dir.with_name(ckpt_dir.name + ".old")
    shutil.rmtree(old, ignore_errors=True)
    if ckpt_dir.exists():
        ckpt_dir.rename(old)
    tmp.rename(ckpt_dir)
    shutil.rmtree(old, ignore_errors=True)


def find(run_dir: Path) -> Path:
    """The newest complete checkpoint of a run folder (survives a kill during ``save``)."""
    base = run_dir / "checkpoints"
    for name in ("last", "last.old"):
        candidate = base / name
        if (candidate / "COMPLETE").exists() and (candidate / "state.pt").exists():
            return candidate
    raise CheckpointError(f"no complete checkpoint under {base} (expected {base / 'last'})")


def load_state(ckpt: Path, cfg: DictConfig | None = None) -> dict[str, Any]:
    """Load ``state.pt``; with ``cfg``, refuse a checkpoint made under a different config."""
    try:
        state = torch.load(ckpt / "state.pt", weights_only=False)
    except Exception as err:  # torch raises several types for a truncated or foreign file
        raise CheckpointError(f"{ckpt / 'state.pt'}: unreadable checkpoint ({err})") from err
    if cfg is not None:
        diff = config_diff(with_legacy_values(state["config"]), comparable(cfg))
        if diff:
            raise CheckpointError(f"{ckpt}: checkpoint made under another config (resume with "
                                  "the checkpoint's values as overrides):\n  " + "\n  ".join(diff))
    return state
