"""Weights files: the one writer and the one reader of every ``.pt`` of weights memrl writes.

``final.pt``, ``checkpoints/stage1.pt``, the self-play pool's snapshots and DAgger's
iterations are each a ``torch.save`` of a dict (weights, architecture, env config, records)
that carries ``sha256``: a SHA-256 of everything else in it (:func:`payload_digest`: keys,
tensors' dtype, shape and bytes, and every other value). :func:`load_weights` recomputes it
and refuses a file whose content changed (one flipped byte in a tensor or in a record),
naming the file. A file written before checksums existed loads with one warning line.
(A resume checkpoint, ``checkpoints/last/``, is checked by its manifest instead:
:mod:`memrl.checkpoint.resume`.)
"""

from __future__ import annotations

import hashlib
import logging
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from memrl.checkpoint.errors import CheckpointError

log = logging.getLogger(__name__)

CHECKSUM_KEY = "sha256"
"""The key of the checksum inside a weights file's dict."""

_warned: set[str] = set()
"""Files already reported as unverified in this process (one line each)."""


def _feed(h: Any, value: Any) -> None:
    """Add ``value`` to the hash ``h`` in a form that two equal payloads share."""
    if isinstance(value, Mapping):
        h.update(b"{")
        for key in sorted(value, key=str):
            _feed(h, str(key))
            _feed(h, value[key])
        h.update(b"}")
    elif isinstance(value, list | tuple):
        h.update(b"(" if isinstance(value, tuple) else b"[")
        for item in value:
            _feed(h, item)
        h.update(b"]")
    elif isinstance(value, torch.Tensor):
        t = value.detach().cpu().contiguous()
        h.update(f"T{t.dtype}{tuple(t.shape)}:".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    elif isinstance(value, np.ndarray):
        a = np.ascontiguousarray(value)
        h.update(f"A{a.dtype}{a.shape}:".encode())
        h.update(a.tobytes())
    else:
        h.update(f"{type(value).__name__}:{value!r};".encode())


def payload_digest(payload: Mapping[str, Any]) -> str:
    """SHA-256 (hex) of a weights file's content, its own ``sha256`` left out."""
    h = hashlib.sha256()
    _feed(h, {k: v for k, v in payload.items() if k != CHECKSUM_KEY})
    return h.hexdigest()


def save_weights(path: str | Path, payload: Mapping[str, Any]) -> Path:
    """Write ``payload`` (a dict of weights and records) with its checksum to ``path``, via a
    temporary file renamed into place (a killed write leaves no truncated file)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save({**payload, CHECKSUM_KEY: payload_digest(payload)}, tmp)
    os.replace(tmp, path)
    return path


def load_weights(path: str | Path, what: str = "weights") -> dict[str, Any]:
    """The dict of a weights file, its checksum checked (on the CPU).

    Raises:
        CheckpointError: ``<file>: damaged weights file ...`` (the checksum differs),
            ``<file>: unreadable <what> (...)`` (truncated, not a torch file) or
            ``<file>: not a memrl <what> file``.
    """
    file = Path(path)
    try:
        state = torch.load(file, weights_only=False, map_location="cpu")
    except Exception as err:  # torch raises several types for a truncated or foreign file
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise CheckpointError(f"{file}: unreadable {what} ({first})") from None
    if not isinstance(state, dict):
        raise CheckpointError(f"{file}: not a memrl {what} file (a {type(state).__name__}, not a dict)")
    stored = state.pop(CHECKSUM_KEY, None)
    if stored is None:
        if str(file.resolve()) not in _warned:
            _warned.add(str(file.resolve()))
            log.warning("%s: written before weights files carried a checksum; loaded unverified", file)
        return state
    if stored != payload_digest(state):
        raise CheckpointError(f"{file}: damaged weights file, its SHA-256 differs from the one "
                              "written with it (restore it or train it again)")
    return state
