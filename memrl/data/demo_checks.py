"""Checks shared by every on-disk demo format: whole files, and values a transition can hold.

Each check raises :class:`DemoDatasetError` with one line naming the file and the problem, so a
damaged or hand-edited dataset is refused at load instead of failing inside the first update.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

import torch
from tensordict import TensorDictBase

from memrl.envs.vehicles import N_ACTIONS

FLAG_KEYS = ("is_demo", "next/done", "next/terminated", "next/truncated")
"""Boolean per-transition keys (nested keys joined by ``/``)."""


class DemoDatasetError(ValueError):
    """A demonstration dataset is missing, damaged, or made for another env or format."""


def tensor_file(root: Path, name: str) -> Path:
    """The ``.memmap`` file of key ``name`` (``/``-joined) in a tensordict memmap folder."""
    *parents, leaf = name.split("/")
    return root.joinpath(*parents) / f"{leaf}.memmap"


def check_files(root: Path, spec: dict[str, tuple[list[int], str]], count: int) -> None:
    """Every tensor file exists, is described with ``[count, *shape]`` and the dtype, and is whole."""
    # Hand-written: tensordict's load_memmap silently zero-extends a truncated file.
    for name, (shape, dtype) in spec.items():
        data = tensor_file(root, name)
        meta_file, leaf = data.parent / "meta.json", data.name.removesuffix(".memmap")
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


def _first_bad(bad: torch.Tensor) -> int:
    return int(bad.reshape(len(bad), -1).any(1).nonzero()[0])


def check_values(td: TensorDictBase, root: Path | Callable[[str], str]) -> None:
    """Actions in ``0..N_ACTIONS-1``, flags 0 or 1 (every row a demo, ``done`` = terminated or
    truncated), rewards finite.

    Args:
        td: per-transition tensors (``action``, ``is_demo``, ``next/*``).
        root: the tensordict memmap folder they were mapped from (messages name its files),
            or a function giving the name to show for a key.
    """
    where = (lambda name: str(tensor_file(root, name))) if isinstance(root, Path) else root
    action = td.get("action")
    bad = (action < 0) | (action >= N_ACTIONS)
    if bad.any():
        i = _first_bad(bad)
        raise DemoDatasetError(f"{where('action')}: action {int(action[i])} at transition "
                               f"{i} is outside 0..{N_ACTIONS - 1}")
    flags = {}
    for name in FLAG_KEYS:
        raw = td.get(tuple(name.split("/"))).view(torch.uint8)  # a bool file may hold any byte
        if (raw > 1).any():
            i = _first_bad(raw > 1)
            raise DemoDatasetError(f"{where(name)}: byte {int(raw[i].max())} at transition "
                                   f"{i} is not a boolean (0 or 1)")
        flags[name] = raw.bool()
    if not bool(flags["is_demo"].all()):
        raise DemoDatasetError(f"{where('is_demo')}: some transitions are not flagged as demos")
    mismatch = flags["next/done"] != (flags["next/terminated"] | flags["next/truncated"])
    if mismatch.any():
        raise DemoDatasetError(f"{where('next/done')}: done differs from terminated or "
                               f"truncated at transition {_first_bad(mismatch)}")
    reward = td.get(("next", "reward"))
    if not bool(torch.isfinite(reward).all()):
        i = _first_bad(~torch.isfinite(reward))
        raise DemoDatasetError(f"{where('next/reward')}: reward {float(reward[i].max())} at "
                               f"transition {i} is not finite")


def check_frame_refs(refs: torch.Tensor, frames: int, file: Path) -> None:
    """Frame references point into the ``frames`` stored frames."""
    bad = (refs < 0) | (refs >= frames)
    if bad.any():
        i = _first_bad(bad)
        raise DemoDatasetError(f"{file}: frame reference {int(refs[i][bad[i]][0])} at transition {i} "
                               f"is outside the {frames} stored frames")
