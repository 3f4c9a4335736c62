"""The format-1 writer of memrl before format 2 (commit 20753fa, ``memrl/data/demos.py``
``save_demos``), kept for tests only: it writes datasets exactly as earlier versions did (both
full stacks per transition in one tensordict memmap), so the loader's backward compatibility is
tested on real format-1 files rather than on a description of them."""

from __future__ import annotations

import dataclasses
import json
import uuid
from collections.abc import Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from tensordict import TensorDictBase

from memrl.data.demos import (
    METADATA_FILE,
    TRANSITIONS_DIR,
    _check_layout,
    _env_values,
    env_config_hash,
    transition_spec,
)


def save_demos_v1(td: TensorDictBase | Sequence[TensorDictBase], path: Path,
                  metadata: Mapping[str, Any]) -> Path:
    """Format 1, as the old ``save_demos`` wrote it (without its temporary-folder dance)."""
    chunks = [td] if isinstance(td, TensorDictBase) else list(td)
    env_config = metadata["env_config"]
    frame_stack = int(metadata.get("frame_stack", 4))
    spec = transition_spec(env_config, frame_stack)
    for chunk in chunks:
        _check_layout(chunk, spec)
    total = sum(c.shape[0] for c in chunks)
    meta = dict(metadata)
    meta.update(
        format_version=1,
        env_config=dataclasses.asdict(_env_values(env_config)),
        env_config_hash=env_config_hash(env_config),
        frame_stack=frame_stack,
        spec={k: {"shape": s, "dtype": d} for k, (s, d) in spec.items()},
        counts={**dict(metadata.get("counts", {})), "transitions": total},
    )
    meta.setdefault("created", datetime.now(UTC).isoformat(timespec="seconds"))
    tmp = path.parent / f".{path.name}.tmp-{uuid.uuid4().hex[:8]}"
    out = chunks[0][0].expand(total).memmap_like(tmp / TRANSITIONS_DIR)
    start = 0
    for chunk in chunks:
        out[start:start + chunk.shape[0]] = chunk
        start += chunk.shape[0]
    del out
    (tmp / METADATA_FILE).write_text(json.dumps(meta, indent=1, default=str))
    tmp.rename(path)
    return path
