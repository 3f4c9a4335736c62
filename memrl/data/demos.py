"""Prior-knowledge datasets: transitions stored exactly as the replay buffer holds them.

A dataset is a folder::

    <name>/metadata.json   format version, env-config hash and config, layout, counts, stats, ...
    <name>/transitions/    tensordict memmap: pixels, action, is_demo, next/{pixels, reward,
                           done, terminated, truncated}; batch size [N]

:func:`save_demos` writes into a hidden temporary folder beside the target and renames it at
the end (``metadata.json`` last), so an interrupted recording never leaves a folder that looks
like a dataset. :func:`load_demos` checks everything before mapping the files and raises
:class:`DemoDatasetError` naming the file and the problem.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import os
import shutil
import uuid
from collections.abc import Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig
from tensordict import TensorDict, TensorDictBase
from torchrl.data.replay_buffers.storages import TensorStorage

from memrl.envs.config import LaneChangeConfig, validate_env_config
from memrl.envs.torchrl_env import env_kwargs

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
"""Version of the on-disk layout; bumped on any incompatible change."""
METADATA_FILE = "metadata.json"
TRANSITIONS_DIR = "transitions"
EPISODE_KEYS = (
    "target_lane", "initial_lane", "initial_speed", "initial_offset", "initial_heading",
    "initial_curvature", "vehicles_count", "other_speed",
    "spawn_ahead", "spawn_behind", "spawn_gap", "spawn_attempts", "opponent", "scene",
)
"""Env-config keys left out of :func:`env_config_hash`: they choose which episodes are drawn
(start and target lanes, the agent's starting pose, how many other cars, where, how fast and
who drives them) or only the picture for people, not what a transition means. Demonstrations recorded with
``initial_lane=non_goal`` therefore load into a run with ``initial_lane=random``; the full
config is still stored in the metadata."""

EnvCfg = Mapping[str, Any] | DictConfig | LaneChangeConfig | None


class DemoDatasetError(ValueError):
    """A demonstration dataset is missing, damaged, or made for another env or format."""


# ----------------------------------------------------------------------------- layout
def _env_values(env_cfg: EnvCfg) -> LaneChangeConfig:
    if isinstance(env_cfg, LaneChangeConfig):
        return validate_env_config(dataclasses.asdict(env_cfg))
    return validate_env_config(env_kwargs(env_cfg))


def _canonical(value: Any) -> Any:
    """JSON-stable form: integral floats as ints (``4.0`` and ``4`` hash alike), tuples as lists."""
    if isinstance(value, dict):
        return {str(k): _canonical(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_canonical(v) for v in value]
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return value


LATER_KEYS: dict[tuple[str, ...], Any] = {("bev", "path_length"): 0.0}
"""Env keys added after datasets were first recorded, with the value that draws what older
versions drew: at that value a key is left out of the hash, so older datasets (and their
hashes) stay valid; any other value changes the hash."""


def hashed_env_config(env_cfg: EnvCfg) -> dict[str, Any]:
    """The part of the validated env config that :func:`env_config_hash` covers."""
    values = dataclasses.asdict(_env_values(env_cfg))
    for (*parents, leaf), neutral in LATER_KEYS.items():
        node = values
        for key in parents:
            node = node[key]
        if node.get(leaf) == neutral:
            del node[leaf]
    return _canonical({k: v for k, v in values.items() if k not in EPISODE_KEYS})


def env_config_hash(env_cfg: EnvCfg) -> str:
    """sha256 of the sorted JSON of the validated env config, without :data:`EPISODE_KEYS`.

    Args:
        env_cfg: a (partial) env config as a mapping, Hydra node or dataclass; None: defaults.
    """
    text = json.dumps(hashed_env_config(env_cfg), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def transition_spec(env_cfg: EnvCfg, frame_stack: int = 4) -> dict[str, tuple[list[int], str]]:
    """Per-transition shape and dtype of every key of
    :data:`memrl.data.transitions.TRANSITION_KEYS` (nested keys joined by ``/``)."""
    bev = _env_values(env_cfg).bev
    pixels = [frame_stack, bev.height, bev.width]
    flag = ([1], "bool")
    return {
        "pixels": (pixels, "uint8"),
        "action": ([], "int64"),
        "is_demo": ([], "bool"),
        "next/pixels": (pixels, "uint8"),
        "next/reward": ([1], "float32"),
        "next/done": flag,
        "next/terminated": flag,
        "next/truncated": flag,
    }


def _key(name: str) -> tuple[str, ...]:
    return tuple(name.split("/"))


def _check_layout(td: TensorDictBase, spec: dict[str, tuple[list[int], str]]) -> None:
    have = {k if isinstance(k, str) else "/".join(k)
            for k in td.keys(include_nested=True, leaves_only=True)}
    if have != set(spec):
        raise ValueError(f"transitions: keys {sorted(have)} != expected {sorted(spec)}")
    for name, (shape, dtype) in spec.items():
        t = td.get(_key(name))
        if list(t.shape[1:]) != shape or str(t.dtype) != f"torch.{dtype}":
            raise ValueError(f"transitions '{name}': {list(t.shape[1:])} {t.dtype}, "
                             f"expected {shape} torch.{dtype}")


# ------------------------------------------------------------------------------- save
def _write_metadata(folder: Path, meta: Mapping[str, Any]) -> None:
    (folder / METADATA_FILE).write_text(json.dumps(meta, indent=1, default=str))


def _fsync_tree(folder: Path) -> None:
    """Flush every file under ``folder`` to disk (a crash then cannot leave zero pages behind
    a metadata file written later)."""
    # Hand-written: tensordict's memmap writes go to the page cache and are never fsynced.
    for file in folder.rglob("*"):
        if file.is_file():
            fd = os.open(file, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)


def save_demos(td: TensorDictBase | Sequence[TensorDictBase], path: str | os.PathLike,
               metadata: Mapping[str, Any], *, overwrite: bool = False) -> Path:
    """Write transitions and ``metadata.json`` atomically (temporary folder, then rename).

    Args:
        td: transitions of batch size [N] in the layout of :func:`transition_spec`, or a
            sequence of such chunks (e.g. one per episode), written one after the other
            without concatenating them in memory first.
        path: dataset folder to create.
        metadata: must hold ``env_config`` (the env config used); anything else (source,
            seed, stats, episode counts, ...) is stored as given. ``format_version``,
            ``env_config_hash``, ``spec``, ``counts.transitions`` and ``created`` are filled in.
        overwrite: replace an existing dataset at ``path`` (it stays valid until the rename).

    Returns:
        The dataset folder.
    """
    path = Path(path)
    chunks = [td] if isinstance(td, TensorDictBase) else list(td)
    if "env_config" not in metadata:
        raise ValueError("save_demos: metadata needs 'env_config' (the env config used)")
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path}: dataset folder exists (use overwrite=True to replace it)")
    env_config = metadata["env_config"]
    frame_stack = int(metadata.get("frame_stack", 4))
    spec = transition_spec(env_config, frame_stack)
    for chunk in chunks:
        _check_layout(chunk, spec)
    total = sum(c.shape[0] for c in chunks)
    if total == 0:
        raise ValueError("save_demos: no transitions to save")
    meta = dict(metadata)
    meta.update(
        format_version=FORMAT_VERSION,
        env_config=dataclasses.asdict(_env_values(env_config)),
        env_config_hash=env_config_hash(env_config),
        frame_stack=frame_stack,
        spec={k: {"shape": s, "dtype": d} for k, (s, d) in spec.items()},
        counts={**dict(metadata.get("counts", {})), "transitions": total},
    )
    meta.setdefault("created", datetime.now(UTC).isoformat(timespec="seconds"))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.tmp-{uuid.uuid4().hex[:8]}"
    try:
        out = chunks[0][0].expand(total).memmap_like(tmp / TRANSITIONS_DIR)
        start = 0
        for chunk in chunks:
            out[start:start + chunk.shape[0]] = chunk
            start += chunk.shape[0]
        del out  # unmap before the rename
        _fsync_tree(tmp)
        _write_metadata(tmp, meta)  # last: a folder without it is never taken for a dataset
        if path.exists():  # overwrite: move the old one aside, then swap
            old = path.parent / f".{path.name}.old-{uuid.uuid4().hex[:8]}"
            path.rename(old)
            tmp.rename(path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            tmp.rename(path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    log.info("saved %d transitions to %s", total, path)
    return path


# ------------------------------------------------------------------------------- load
def read_metadata(path: str | os.PathLike) -> dict[str, Any]:
    """The parsed ``metadata.json`` of a dataset folder, with the format version checked."""
    path = Path(path)
    if not path.is_dir():
        raise DemoDatasetError(f"{path}: no dataset folder there")
    file = path / METADATA_FILE
    if not file.is_file():
        raise DemoDatasetError(f"{file}: missing; not a memrl demo dataset, or an unfinished one")
    try:
        meta = json.loads(file.read_text())
    except (OSError, ValueError) as e:
        raise DemoDatasetError(f"{file}: unreadable JSON ({e})") from None
    missing = [k for k in ("format_version", "env_config", "env_config_hash", "spec", "counts")
               if k not in meta]
    if missing:
        raise DemoDatasetError(f"{file}: missing field(s) {missing}")
    if meta["format_version"] != FORMAT_VERSION:
        raise DemoDatasetError(f"{file}: format version {meta['format_version']!r}; this memrl "
                               f"reads version {FORMAT_VERSION} (re-record the dataset)")
    return meta


def _check_env(file: Path, meta: dict[str, Any], env_cfg: EnvCfg) -> None:
    try:
        stored = hashed_env_config(meta["env_config"])
    except ValueError as e:
        raise DemoDatasetError(f"{file}: bad 'env_config' ({e})") from None
    if env_config_hash(meta["env_config"]) != meta["env_config_hash"]:
        raise DemoDatasetError(f"{file}: 'env_config_hash' does not match its 'env_config' (edited?)")
    if env_cfg is None:
        return
    wanted = env_config_hash(env_cfg)
    if wanted != meta["env_config_hash"]:
        ours = hashed_env_config(env_cfg)
        diff = sorted(k for k in set(ours) | set(stored) if ours.get(k) != stored.get(k))
        details = ", ".join(f"{k}: dataset {stored.get(k)!r} vs env {ours.get(k)!r}" for k in diff)
        raise DemoDatasetError(
            f"{file}: env-config hash mismatch (dataset {meta['env_config_hash'][:12]}, "
            f"env {wanted[:12]}); differing keys: {details}")


def _check_files(root: Path, spec: dict[str, tuple[list[int], str]], count: int) -> None:
    """Every tensor file exists, is described with the expected shape and dtype, and is whole."""
    # Hand-written: tensordict's load_memmap silently zero-extends a truncated file.
    for name, (shape, dtype) in spec.items():
        *parents, leaf = name.split("/")
        folder = root.joinpath(*parents)
        data, meta_file = folder / f"{leaf}.memmap", folder / "meta.json"
        if not data.is_file():
            raise DemoDatasetError(f"{data}: missing tensor file for '{name}'")
        try:
            described = json.loads(meta_file.read_text())[leaf]
        except (OSError, ValueError, KeyError) as e:
            raise DemoDatasetError(f"{meta_file}: no readable description of '{leaf}' ({e!r})") from None
        expected = [count, *shape]
        if described.get("shape") != expected or described.get("dtype") != f"torch.{dtype}":
            raise DemoDatasetError(
                f"{data}: stored as {described.get('shape')} {described.get('dtype')}, "
                f"expected {expected} torch.{dtype}")
        size = math.prod(expected) * torch.empty((), dtype=getattr(torch, dtype)).element_size()
        if data.stat().st_size != size:
            raise DemoDatasetError(f"{data}: {data.stat().st_size} bytes, expected {size} "
                                   f"(truncated or overwritten file)")


def load_demos(path: str | os.PathLike, env_cfg: EnvCfg = None) -> TensorDict:
    """Map a dataset into memory after checking it.

    Args:
        path: dataset folder written by :func:`save_demos`.
        env_cfg: the env config the transitions will be used with; when given, its
            :func:`env_config_hash` must equal the dataset's.

    Returns:
        Memory-mapped transitions, batch size [N]. Do not write into them: the files change.

    Raises:
        DemoDatasetError: naming the file and the problem.
    """
    path = Path(path)
    meta = read_metadata(path)
    file = path / METADATA_FILE
    _check_env(file, meta, env_cfg)
    spec = transition_spec(meta["env_config"], int(meta.get("frame_stack", 4)))
    stored_spec = {k: (v.get("shape"), v.get("dtype")) for k, v in meta["spec"].items()}
    if stored_spec != spec:
        raise DemoDatasetError(f"{file}: 'spec' {stored_spec} does not match the layout {spec}")
    count = meta["counts"].get("transitions")
    if not isinstance(count, int) or count < 1:
        raise DemoDatasetError(f"{file}: 'counts.transitions' must be a positive int, got {count!r}")
    root = path / TRANSITIONS_DIR
    _check_files(root, spec, count)
    try:
        td = TensorDict.load_memmap(root)
    except Exception as e:  # tensordict raises assorted types for damaged folders
        raise DemoDatasetError(f"{root}: cannot be mapped ({e!r})") from None
    try:
        _check_layout(td, spec)
    except ValueError as e:
        raise DemoDatasetError(f"{root}: {e}") from None
    if not bool(td["is_demo"].all()):
        raise DemoDatasetError(f"{root / 'is_demo.memmap'}: some transitions are not flagged as demos")
    return td  # type: ignore[return-value]


def dataset_bytes(path: str | os.PathLike) -> int:
    """Size on disk of a dataset folder [bytes] (sum of its files)."""
    return sum(f.stat().st_size for f in Path(path).rglob("*") if f.is_file())


# --------------------------------------------------------------------------- storage
def demos_into_storage(td: TensorDictBase, storage: TensorStorage, *, start: int = 0,
                       chunk: int = 2048) -> slice:
    """Copy transitions into rows ``[start, start + N)`` of a TorchRL tensor storage.

    Reads the memory-mapped files straight into the storage's tensors, ``chunk`` rows at a
    time: one copy, no intermediate in-memory TensorDict. Works for ``LazyTensorStorage``
    (RAM) and ``LazyMemmapStorage`` (disk) alike; a lazy storage is laid out from the first
    rows. The storage's length grows by N (TorchRL counts written rows).

    Returns:
        The rows written.
    """
    n = td.shape[0]
    if start < 0 or start + n > storage.max_size:
        raise ValueError(f"demos_into_storage: rows [{start}, {start + n}) do not fit a storage "
                         f"of {storage.max_size}")
    for i in range(0, n, chunk):
        j = min(i + chunk, n)
        storage.set(slice(start + i, start + j), td[i:j])
    return slice(start, start + n)


# --------------------------------------------------------------------------- example
def default_data_dir() -> Path:
    """``$MEMRL_ROOT/outputs/data`` (``./outputs/data`` without the variable), as ``paths``."""
    return Path(os.environ.get("MEMRL_ROOT", ".")) / "outputs" / "data"


def example_demos_path(env_cfg: EnvCfg = None, data_dir: str | os.PathLike | None = None) -> Path:
    """Where the cached scripted-driver example for this env config lives."""
    folder = Path(data_dir) if data_dir is not None else default_data_dir()
    return folder / f"example_scripted_{env_config_hash(env_cfg)[:12]}"


def ensure_example_demos(env_cfg: EnvCfg = None, data_dir: str | os.PathLike | None = None, *,
                         episodes: int = 10, seed: int = 0, overwrite: bool = False) -> Path:
    """Path of the cached example dataset made by the scripted driver; records it if needed.

    The dataset is recorded with ``env_cfg`` (keeping stable episodes only) and cached under
    ``data_dir`` by env-config hash. A cached dataset that fails :func:`load_demos` is
    recorded again.
    """
    from memrl.data.recording import record_to_dataset  # recording needs the env stack
    from memrl.modules.scripted import ScriptedDriver

    path = example_demos_path(env_cfg, data_dir)
    if path.exists() and not overwrite:
        try:
            load_demos(path, env_cfg)
            return path
        except DemoDatasetError as e:
            log.warning("cached example dataset is unusable, recording it again: %s", e)
    log.info("recording the example dataset (%d scripted episodes) into %s", episodes, path)
    saved, rec = record_to_dataset(
        env_cfg, ScriptedDriver(), path, episodes=episodes, seed=seed, keep_stable=True,
        source="scripted", overwrite=True,
        extra={"policy": {"_target_": "memrl.modules.scripted.ScriptedDriver"}, "example": True})
    if saved is None:
        raise RuntimeError(f"the scripted driver kept no stable episode out of {episodes}; "
                           f"recorded: {rec.stats()['recorded']}")
    return path
