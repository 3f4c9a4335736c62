"""Prior-knowledge datasets: each 84x84 frame stored once, transitions rebuilt on load.

A dataset (format version 2) is a folder::

    <name>/metadata.json   format version, env-config hash and config, layout, counts, stats, ...
    <name>/frames.npz      pixels [F, H, W] uint8, every frame once (numpy, deflate-compressed)
    <name>/transitions/    tensordict memmap: frame_refs [N, stack + 1] (indices into frames: the
                           stack of ``pixels``, then the newest frame of ``next/pixels``), action,
                           is_demo, next/{reward, done, terminated, truncated}; batch size [N]

The refs are the replay's frame ring's (:func:`memrl.data.frame_plan.plan_write`), with the
ring as large as the dataset: an episode of T steps stores T + 1 frames, not 8 T, and the flat
shades of the BEV deflate about 80x. Version 1
(``transitions/`` holding both full stacks per transition, 8x the frames) still loads.
:func:`load_demos` gives the same transitions from either version: ``pixels`` and
``("next", "pixels")`` ``[stack, H, W]``, as the env pipeline and the replay buffers use them.

:func:`save_demos` writes into a hidden temporary folder beside the target and renames it at
the end (``metadata.json`` last), so an interrupted recording never leaves a folder that looks
like a dataset. :func:`load_demos` checks files and values before use and raises
:class:`DemoDatasetError` naming the file and the problem.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import shutil
import uuid
from collections.abc import Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig
from tensordict import TensorDict, TensorDictBase
from torchrl.data.replay_buffers.storages import TensorStorage

from memrl.data.demo_checks import (
    DemoDatasetError,
    check_files,
    check_frame_refs,
    check_values,
    tensor_file,
)
from memrl.data.frame_plan import Pixels, not_shifted_message, plan_write
from memrl.data.frame_store import REFS_KEY
from memrl.data.recipe import recipe_hash, recipe_values
from memrl.data.stride_plan import not_strided_message, plan_strided
from memrl.envs.config import LaneChangeConfig, validate_env_config
from memrl.envs.torchrl_env import env_kwargs

log = logging.getLogger(__name__)

FORMAT_VERSION = 2
"""Version of the on-disk layout written; bumped on any incompatible change."""
READABLE_VERSIONS = (1, 2)
"""Versions :func:`load_demos` reads (1: full stacks per transition)."""
METADATA_FILE = "metadata.json"
TRANSITIONS_DIR = "transitions"
FRAMES_FILE = "frames.npz"
PIXELS = ("pixels", ("next", "pixels"))
EPISODE_KEYS = (
    "target_lane", "initial_lane", "initial_speed", "initial_offset", "initial_heading",
    "initial_curvature", "vehicles_count", "other_speed",
    "spawn_ahead", "spawn_behind", "spawn_gap", "spawn_attempts", "opponent", "scene",
    "num_envs",  # how many envs a trainer steps at once: the same task, the same transitions
)
"""Env-config keys left out of :func:`env_config_hash`: they choose which episodes are drawn
(start and target lanes, the agent's starting pose, how many other cars, where, how fast and
who drives them) or only the picture for people, not what a transition means. Demonstrations recorded with
``initial_lane=non_goal`` therefore load into a run with ``initial_lane=random``; the full
config is still stored in the metadata."""

EnvCfg = Mapping[str, Any] | DictConfig | LaneChangeConfig | None


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


LATER_KEYS: dict[tuple[str, ...], Any] = {("bev", "path_length"): 0.0, ("frame_stack",): 1,
                                          ("frame_stride",): 1, ("bev", "path_time"): 0.0,
                                          ("shaping",): {"weight": 0.0, "horizon": 3.0, "gamma": 0.95}}
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


def stored_spec(spec: dict[str, tuple[list[int], str]],
                stride: int = 1) -> dict[str, tuple[list[int], str]]:
    """Per-transition files of format 2: :func:`transition_spec` with both stacks replaced by
    ``frame_refs`` (``stack + 1`` indices into ``frames/``; ``2 stack`` for strided stacks)."""
    stack = spec["pixels"][0][0]
    out = {k: v for k, v in spec.items() if k not in ("pixels", "next/pixels")}
    out[REFS_KEY] = ([stack + 1 if stride == 1 else 2 * stack], "int64")
    return out


def frame_stride(env_cfg: EnvCfg, metadata: Mapping[str, Any] | None = None) -> int:
    """Frames between stacked frames of a dataset: its metadata's ``frame_stride``, else the env
    config's ``frame_stride``, else 1 (datasets recorded before strided stacks)."""
    if metadata is not None and "frame_stride" in metadata:
        return int(metadata["frame_stride"])
    return int(getattr(_env_values(env_cfg), "frame_stride", 1))


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


def compact_frames(chunks: Sequence[TensorDictBase],
                   stride: int = 1) -> tuple[torch.Tensor, list[TensorDictBase]]:
    """Every frame of the chunks once, and the chunks with their two stacks replaced by
    ``frame_refs`` into those frames (the frame ring's plan, with a ring as large as the data).

    Raises:
        ValueError: where ``("next", "pixels")`` is not ``pixels`` shifted by one frame (by
            one step of ``stride`` frames apart stacks).
    """
    if stride != 1:
        return _compact_strided(chunks, stride)
    ops, head, prev_refs, prev_stack = Pixels(numpy=True), 0, None, None
    frames: list[np.ndarray] = []
    out: list[TensorDictBase] = []
    for chunk in chunks:
        p, q = chunk.get("pixels").numpy(), chunk.get(("next", "pixels")).numpy()
        plan = plan_write(p, q, head, 1, prev_refs, prev_stack, ops)
        pushes, _, bad = plan.read_stats()
        if bad:
            ok = (q[:, :-1] == p[:, 1:]).reshape(len(p), -1).all(1)
            raise ValueError(not_shifted_message(int(np.flatnonzero(~ok)[0])))
        # pushes are consecutive counters in row-major order of ``pushed``: frame j < stack of
        # a row is pixels[:, j], frame stack is next_pixels[:, -1]
        frames.append(np.concatenate([p, q[:, -1:]], 1)[plan.pushed])
        head, prev_refs, prev_stack = head + pushes, plan.refs[-1:, 1:], q[-1:]
        rest = chunk.exclude(*PIXELS)
        rest.set(REFS_KEY, torch.from_numpy(plan.refs))
        out.append(rest)
    return torch.from_numpy(np.concatenate(frames)), out


def _compact_strided(chunks: Sequence[TensorDictBase],
                     stride: int) -> tuple[torch.Tensor, list[TensorDictBase]]:
    """:func:`compact_frames` of strided stacks: ``2 stack`` refs per transition."""
    head, hist, hist_frames, start = 0, None, None, 0
    frames: list[torch.Tensor] = []
    out: list[TensorDictBase] = []
    for chunk in chunks:
        plan = plan_strided(chunk.get("pixels"), chunk.get(("next", "pixels")), head, 1, stride,
                            hist, hist_frames)
        if plan.bad >= 0:
            raise ValueError(not_strided_message(start + plan.bad, stride))
        frames.append(plan.pushed)  # in counter order
        head, hist, hist_frames = head + len(plan.pushed), plan.hist, plan.hist_frames
        start += chunk.shape[0]
        rest = chunk.exclude(*PIXELS)
        rest.set(REFS_KEY, plan.refs)
        out.append(rest)
    return torch.cat(frames), out


def save_demos(td: TensorDictBase | Sequence[TensorDictBase], path: str | os.PathLike,
               metadata: Mapping[str, Any], *, overwrite: bool = False) -> Path:
    """Write transitions (each frame once) and ``metadata.json`` atomically (temporary folder,
    then rename).

    Args:
        td: transitions of batch size [N] in the layout of :func:`transition_spec`, or a
            sequence of such chunks (e.g. one per episode), written one after the other
            without concatenating them in memory first. ``("next", "pixels")`` must be
            ``pixels`` shifted by one frame (as ``CatFrames`` makes it).
        path: dataset folder to create.
        metadata: must hold ``env_config`` (the env config used); anything else (source,
            seed, stats, episode counts, ...) is stored as given. ``format_version``,
            ``env_config_hash``, ``spec``, ``counts.transitions``, ``counts.frames`` and
            ``created`` are filled in.
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
    chunks = [c for c in chunks if c.shape[0]]
    total = sum(c.shape[0] for c in chunks)
    if total == 0:
        raise ValueError("save_demos: no transitions to save")
    stride = frame_stride(env_config, metadata)
    frames, stored = compact_frames(chunks, stride)
    meta = dict(metadata)
    if stride != 1:  # datasets of k = 1 keep the older metadata
        meta["frame_stride"] = stride
    meta.update(
        format_version=FORMAT_VERSION,
        env_config=dataclasses.asdict(_env_values(env_config)),
        env_config_hash=env_config_hash(env_config),
        frame_stack=frame_stack,
        spec={k: {"shape": s, "dtype": d} for k, (s, d) in spec.items()},
        counts={**dict(metadata.get("counts", {})), "transitions": total, "frames": len(frames)},
    )
    meta.setdefault("created", datetime.now(UTC).isoformat(timespec="seconds"))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.tmp-{uuid.uuid4().hex[:8]}"
    try:
        tmp.mkdir()
        # numpy, not a tensordict memmap: memmaps cannot be compressed, and BEV frames (flat
        # shades) deflate about 80x; format 2 is gathered into memory on load anyway.
        np.savez_compressed(tmp / FRAMES_FILE, pixels=frames.numpy())
        out = stored[0][0].expand(total).memmap_like(tmp / TRANSITIONS_DIR)
        start = 0
        for chunk in stored:
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
    log.info("saved %d transitions (%d frames) to %s", total, len(frames), path)
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
    if meta["format_version"] not in READABLE_VERSIONS:
        raise DemoDatasetError(f"{file}: format version {meta['format_version']!r}; this memrl "
                               f"reads versions {list(READABLE_VERSIONS)} (re-record the dataset)")
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


def _count(file: Path, meta: dict[str, Any], name: str) -> int:
    count = meta["counts"].get(name)
    if not isinstance(count, int) or isinstance(count, bool) or count < 1:
        raise DemoDatasetError(f"{file}: 'counts.{name}' must be a positive int, got {count!r}")
    return count


def _map(root: Path, spec: dict[str, tuple[list[int], str]]) -> TensorDictBase:
    """The tensordict memmap at ``root``, with the files' layout checked against ``spec``."""
    try:
        td = TensorDict.load_memmap(root)
    except Exception as e:  # tensordict raises assorted types for damaged folders
        raise DemoDatasetError(f"{root}: cannot be mapped ({e!r})") from None
    try:
        _check_layout(td, spec)
    except ValueError as e:
        raise DemoDatasetError(f"{root}: {e}") from None
    return td


def _read_frames(file: Path, shape: list[int], dtype: str) -> np.ndarray:
    """The frames of ``frames.npz``, checked to be ``shape`` of ``dtype``."""
    try:
        with np.load(file, allow_pickle=False) as npz:
            frames = npz["pixels"]
    except FileNotFoundError:
        raise DemoDatasetError(f"{file}: missing frames file") from None
    except Exception as e:  # zipfile, zlib and numpy raise assorted types for damaged files
        raise DemoDatasetError(f"{file}: unreadable frames ({e!r})") from None
    if list(frames.shape) != shape or str(frames.dtype) != dtype:
        raise DemoDatasetError(f"{file}: frames {list(frames.shape)} {frames.dtype}, "
                               f"expected {shape} {dtype}")
    return frames


def _load_v1(path: Path, spec: dict[str, tuple[list[int], str]], count: int) -> TensorDictBase:
    """Format 1: both stacks stored per transition; mapped as they are."""
    root = path / TRANSITIONS_DIR
    check_files(root, spec, count)
    td = _map(root, spec)
    check_values(td, root)
    return td


def _load_v2(path: Path, spec: dict[str, tuple[list[int], str]], count: int,
             frames: int, stride: int = 1) -> TensorDictBase:
    """Format 2: frames once plus refs; both stacks gathered into memory (numpy's gather)."""
    root = path / TRANSITIONS_DIR
    check_files(root, stored_spec(spec, stride), count)
    shape, dtype = spec["pixels"]
    ring = _read_frames(path / FRAMES_FILE, [frames, *shape[1:]], dtype)
    td = _map(root, stored_spec(spec, stride))
    check_values(td, root)
    refs = td.get(REFS_KEY)
    check_frame_refs(refs, frames, tensor_file(root, REFS_KEY))
    stack, slots = spec["pixels"][0][0], refs.numpy()
    out = td.exclude(REFS_KEY).to_tensordict()
    out.set("pixels", torch.from_numpy(ring[slots[:, :stack]]))
    nxt = slots[:, stack:] if stride != 1 else slots[:, 1:]
    out.set(("next", "pixels"), torch.from_numpy(ring[nxt]))
    return out


def load_demos(path: str | os.PathLike, env_cfg: EnvCfg = None) -> TensorDict:
    """Load a dataset after checking it: files, layout and values (actions in range, boolean
    flags, finite rewards, frame references inside the stored frames).

    Args:
        path: dataset folder written by :func:`save_demos` (format 2, or format 1 of earlier
            memrl versions).
        env_cfg: the env config the transitions will be used with; when given, its
            :func:`env_config_hash` must equal the dataset's.

    Returns:
        Transitions of batch size [N] in the layout of :func:`transition_spec`, the same from
        either format. Format 2 is rebuilt in memory; format 1 is memory-mapped (do not write
        into it: the files change).

    Raises:
        DemoDatasetError: naming the file and the problem.
    """
    path = Path(path)
    meta = read_metadata(path)
    file = path / METADATA_FILE
    _check_env(file, meta, env_cfg)
    spec = transition_spec(meta["env_config"], int(meta.get("frame_stack", 4)))
    stored = {k: (v.get("shape"), v.get("dtype")) for k, v in meta["spec"].items()}
    if stored != spec:
        raise DemoDatasetError(f"{file}: 'spec' {stored} does not match the layout {spec}")
    count = _count(file, meta, "transitions")
    if meta["format_version"] == 1:
        return _load_v1(path, spec, count)  # type: ignore[return-value]
    return _load_v2(path, spec, count, _count(file, meta, "frames"),  # type: ignore[return-value]
                    frame_stride(meta["env_config"], meta))


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


RECORDING_OPPONENT = {"type": "constant"}
"""Other cars of the scripted example dataset: constant speed, as the paper's prior knowledge,
also for runs trained among learned or mixed traffic (one dataset for both, recorded without
the pool's networks; other traffic: ``python -m memrl.record`` and ``mode.demos_path``)."""


def recording_env(env_cfg: EnvCfg, recipe: Any) -> dict[str, Any]:
    """The env a recipe records in: ``env_cfg`` with the recipe's episode keys on top and the
    other cars at constant speed (:data:`RECORDING_OPPONENT`), whatever the training traffic."""
    return {**dataclasses.asdict(_env_values(env_cfg)), **recipe_values(recipe)["env"],
            "opponent": dict(RECORDING_OPPONENT)}


def example_demos_path(env_cfg: EnvCfg = None, data_dir: str | os.PathLike | None = None,
                       recipe: Any = None) -> Path:
    """Where the cached scripted-driver example of this env config and recipe lives
    (``recipe``: a :class:`memrl.data.recipe.DemoRecipe` or its values; None: the default).

    The name holds the env config's hash (what a transition means), the recipe's, and that of
    the episode keys it records with (:func:`recording_env`): two training envs that draw
    other episodes (``env.other_speed``, ``env.spawn_gap`` ...) get datasets of their own."""
    folder = Path(data_dir) if data_dir is not None else default_data_dir()
    meaning, episodes = env_config_hash(env_cfg), episode_keys_hash(recording_env(env_cfg, recipe))
    return folder / f"example_scripted_{meaning[:12]}_{recipe_hash(recipe)[:8]}_{episodes[:8]}"


def episode_keys_hash(env_cfg: EnvCfg) -> str:
    """sha256 of the :data:`EPISODE_KEYS` values that decide which episodes a recording draws
    (``num_envs`` and ``scene``, which do not, left out)."""
    values = dataclasses.asdict(_env_values(env_cfg))
    drawn = {k: values[k] for k in EPISODE_KEYS if k not in ("num_envs", "scene")}
    text = json.dumps(_canonical(drawn), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()
