"""Resume checkpoints (``checkpoints/last/``): atomic save of everything a run needs to continue
exactly, their manifests, and safe loading; what a run recorded of its config."""

from __future__ import annotations

import copy
import json
import random
import shutil
import zlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from memrl.checkpoint.errors import CheckpointError
from memrl.checkpoint.weights import load_weights
from memrl.data.recipe import LEGACY_RECIPE
from memrl.modes import used

RUNTIME_KEYS = ("resume", "overwrite", "paths", "logger", "progress", "total_frames", "total_episodes",
                "checkpoint_every", "log_every", "hydra", "device", "eval", "seeds_engine")
"""Config keys that may differ between a run and its resumption (outputs and budgets; the
periodic evaluation ``eval`` leaves the training's RNG and weights as they are; a group's
``seeds_engine`` hosts the same envs either way)."""


LEGACY_VALUES: dict[str, Any] = {
    "variant": None,
    "buffer": {"crash_share": 0.0, "priority": 0.0, "priority_beta": 0.5},
    "network": {"_target_": "memrl.modules.qnet.QNetwork", "channels": 16, "hidden": 256,
                "layernorm": False, "layernorm_convs": False},  # conf/network/table1.yaml
    "agent": {"precision": "float32", "overlap": False, "exploration": "epsilon", "ez_mu": 2.0,
              "ez_max_duration": 50, "temperature_start": 1.0, "temperature_end": 0.05,
              "n_step": 1, "augment_shift": 0, "advantage_learning": 0.0},
    "env": {"bev": {"path_length": 0.0, "path_time": 0.0}, "initial_offset": 0.0, "initial_heading": 0.0,
            "initial_curvature": 0.0, "frame_stack": 1, "num_envs": 1,
            "frame_stride": 1, "shaping": {"weight": 0.0, "horizon": 3.0, "gamma": 0.95}},
    "mode": {"stage1": {"lr": None, "drive_episodes": 0, "drive_seed": 0, "drive_target": 0.9,
                        "keep_best": True, "init": None},
             "stage2": {"demo_fraction": 0.0, "margin_weight": 0.0, "lr": None, "n_step": None},
             "margin_weight": 0.0,
             "example": LEGACY_RECIPE},
}
"""Keys added to the config after checkpoints were first written, at the value that does what
the versions before them did: a checkpoint without a key is compared as if it held this
value, so resuming it asks for exactly that value (``agent.overlap=false`` ...)."""


LEGACY_NODES = ("example", "network", "shaping")
"""Keys of :data:`LEGACY_VALUES` whose value is a whole node added at once (other dict values
only descend into the nodes a config has)."""


def with_legacy_values(config: dict[str, Any], legacy: dict[str, Any] = LEGACY_VALUES,
                       ) -> dict[str, Any]:
    """``config`` with the keys of ``legacy`` that it lacks filled in (nested)."""
    out = dict(config)
    for key, value in legacy.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = with_legacy_values(out[key], value)
        elif key not in out and (not isinstance(value, dict) or key in LEGACY_NODES):
            out[key] = copy.deepcopy(value)
    return out


MANIFEST = "MANIFEST.json"
"""Size and CRC-32 of every file of a checkpoint, written with it and checked before loading."""


def rng_state() -> dict[str, Any]:
    state = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(),
             "python": random.getstate()}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    if "cuda" in state and torch.cuda.is_available():  # a CPU resume of a CUDA run skips it
        torch.cuda.set_rng_state_all(state["cuda"])


def comparable(cfg: DictConfig) -> dict[str, Any]:
    """The part of a config that must match for a checkpoint to be resumed."""
    data = OmegaConf.to_container(cfg, resolve=False)
    assert isinstance(data, dict)
    return without_runtime_keys(data)


def without_runtime_keys(config: Mapping[Any, Any]) -> dict[str, Any]:
    """``config`` without :data:`RUNTIME_KEYS` (also those an older checkpoint stored: eval)."""
    return {str(k): v for k, v in config.items() if k not in RUNTIME_KEYS}


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


def file_crc32(path: Path, chunk: int = 1 << 23) -> int:
    """CRC-32 of a file's bytes (zlib's: about 3 GB/s, so a 1.4 GB buffer costs ~0.5 s)."""
    crc = 0
    with path.open("rb") as f:
        while block := f.read(chunk):
            crc = zlib.crc32(block, crc)
    return crc


def write_manifest(ckpt_dir: Path) -> dict[str, Any]:
    """Record the size and checksum of every file under ``ckpt_dir`` in :data:`MANIFEST`."""
    files = {p.relative_to(ckpt_dir).as_posix(): {"bytes": p.stat().st_size, "crc32": file_crc32(p)}
             for p in sorted(ckpt_dir.rglob("*")) if p.is_file() and p.name != MANIFEST}
    doc = {"format": 1, "files": files}
    (ckpt_dir / MANIFEST).write_text(json.dumps(doc, indent=1))
    return doc


def check_manifest(ckpt_dir: Path) -> None:
    """Refuse a checkpoint whose files differ from its manifest, naming the first bad file.

    A checkpoint without its manifest cannot be verified and is refused (checkpoints written
    before manifests existed: write one with :func:`write_manifest` once the files are known
    good).
    """
    file = ckpt_dir / MANIFEST
    if not file.is_file():
        raise CheckpointError(f"{file}: missing, so the checkpoint cannot be verified; cannot resume "
                              "from it (a checkpoint from before manifests: python -c \"from "
                              "memrl.checkpoint.resume import write_manifest as w; "
                              f"w(__import__('pathlib').Path('{ckpt_dir}'))\" if its files are good)")
    try:
        files = json.loads(file.read_text())["files"]
    except (ValueError, KeyError) as err:
        raise CheckpointError(f"{file}: unreadable checkpoint manifest ({err})") from None
    for name, want in files.items():
        path = ckpt_dir / name
        if not path.is_file():
            raise CheckpointError(f"{path}: missing from the checkpoint (listed in {MANIFEST})")
        size = path.stat().st_size
        if size != want["bytes"]:
            raise CheckpointError(f"{path}: damaged checkpoint file, {size} bytes where "
                                  f"{want['bytes']} were written; cannot resume from it")
        if file_crc32(path) != want["crc32"]:
            raise CheckpointError(f"{path}: damaged checkpoint file, its CRC-32 differs from the "
                                  "one written with it; cannot resume from it")


def save(ckpt_dir: Path, state: dict[str, Any], buffer: Any | None) -> None:
    """Write ``state.pt``, the buffer and their manifest into a temporary folder, then swap it
    in atomically. A failed write (a full disk) names the folder and the free space."""
    tmp = ckpt_dir.with_name(ckpt_dir.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        tmp.mkdir(parents=True)
        torch.save(state, tmp / "state.pt")
        if buffer is not None:
            buffer.dumps(tmp / "buffer")
        write_manifest(tmp)
        (tmp / "COMPLETE").write_text("ok\n")
    except (OSError, RuntimeError) as err:  # torch reports a short write as RuntimeError
        shutil.rmtree(tmp, ignore_errors=True)
        free = shutil.disk_usage(ckpt_dir.parent if ckpt_dir.parent.exists() else Path(".")).free
        raise CheckpointError(f"{tmp}: writing the checkpoint failed with {free / 1e6:.0f} MB free "
                              f"on its disk (full disk?): {str(err).splitlines()[0]}") from err
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
    """Check the checkpoint's files against its manifest and load ``state.pt``; with ``cfg``,
    refuse a checkpoint made under a different config."""
    check_manifest(ckpt)
    try:
        state = torch.load(ckpt / "state.pt", weights_only=False, map_location="cpu")
    except Exception as err:  # torch raises several types for a truncated or foreign file
        raise CheckpointError(f"{ckpt / 'state.pt'}: unreadable checkpoint ({err})") from err
    if cfg is not None:
        stored = without_runtime_keys(state["config"])
        diff = config_diff(used(with_legacy_values(stored)), used(comparable(cfg)))
        if diff:
            raise CheckpointError(f"{ckpt}: checkpoint made under another config (resume with "
                                  "the checkpoint's values as overrides):\n  " + "\n  ".join(diff))
    return state


def recorded_config(run: Path) -> tuple[dict[str, Any] | None, Path | None]:
    """What a run recorded of its config besides ``config.yaml``, and where: ``mode``,
    ``seed`` and ``variant`` from its newest complete checkpoint (manifest-checked), else the
    mode and seed of the summary in ``checkpoints/final.pt`` (or ``summary.json``); ``env``:
    the resolved env config ``final.pt`` stores. (None, None) when it recorded neither."""
    final = run / "checkpoints" / "final.pt"
    state = load_weights(final, "Q-network weights") if final.is_file() else {}
    env = state.get("env") or {}
    try:
        last: Path | None = find(run)
    except CheckpointError:  # no checkpoint kept (a copied run): the final network's records
        last = None
    if last is not None:
        stored = load_state(last)["config"]
        return {"mode": stored.get("mode") or {}, "seed": stored.get("seed"),
                "variant": stored.get("variant"), "env": env}, last / "state.pt"
    summary, source = state.get("summary"), final
    if not isinstance(summary, dict) and (run / "summary.json").is_file():
        try:
            summary, source = json.loads((run / "summary.json").read_text()), run / "summary.json"
        except ValueError:  # garbled: not a record
            summary = None
    if not isinstance(summary, dict) or "mode" not in summary or "seed" not in summary:
        return None, None
    return {"mode": {"name": summary["mode"]}, "seed": summary["seed"], "env": env}, source
