"""Fig. 7-style strips of crashes: the last frames before the collision, a few per kind.

The episodes are replayed from their scene seeds with the evaluated policy (as Fig. 7's,
:func:`memrl.evaluation.rollouts.capture`); each row shows the scene pictures of the last
``frames`` steps up to the crash, captioned with the crash's kind, closing speed and cars.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from memrl.envs.crash import CRASH_KINDS
from memrl.evaluation import rollouts
from memrl.evaluation.protocol import EpisodeRecord
from memrl.evaluation.results import EvalResult
from memrl.evaluation.runner import Actor


def crash_records(result: EvalResult, kind: str, count: int) -> list[EpisodeRecord]:
    """The first ``count`` episodes of ``result`` (non-goal starts first) that crashed as ``kind``."""
    recs = [r for r in result.records() if r.collided and r.crash_kind == kind]
    recs.sort(key=lambda r: (r.initial_lane != "non_goal", r.episode))
    return recs[:count]


def _caption(c: rollouts.Capture, i: int) -> str:
    r = c.record
    speed = "" if r.closing_speed is None else f", closing speed {r.closing_speed:.2f} m/s"
    return (f"({chr(97 + i)}) {r.initial_lane.replace('_', '-')} episode {r.episode}, scene seed {r.seed}, "
            f"{r.vehicles} car{'' if r.vehicles == 1 else 's'}: {r.crash_kind} at step {r.steps}{speed}")


def crash_strip(captures: Sequence[rollouts.Capture], frames: int, title: str, scale: float = 1.0,
                gap: int = 6) -> np.ndarray:
    """One row per replayed crash: its last ``frames`` scene pictures (the crash last); RGB."""
    rows = []
    for i, c in enumerate(captures):
        end = len(c.scenes) - 1
        tiles = []
        for k in range(max(0, end - frames + 1), end + 1):
            img = cv2.resize(c.scenes[k], None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
            tiles += [rollouts._label(img, f"step {k}" + (" (crash)" if k == end else "")),
                      np.full((img.shape[0] + 22, gap, 3), 255, np.uint8)]
        row = np.concatenate(tiles[:-1], axis=1)
        rows += [rollouts._band(row.shape[1], _caption(c, i), scale=0.42), row,
                 np.full((gap, row.shape[1], 3), 255, np.uint8)]
    width = max(r.shape[1] for r in rows)
    rows = [rollouts._band(width, title, 28, scale=0.55), *rows, rollouts.legend(width)]
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0)), constant_values=255) for r in rows]
    return np.concatenate(rows)


def crash_strips(actor: Actor, result: EvalResult, label: str, count: int, frames: int,
                 scale: float = 1.0) -> dict[str, np.ndarray]:
    """Kind -> strip of up to ``count`` replayed crashes of that kind (kinds without one left out)."""
    out = {}
    for kind in CRASH_KINDS:
        recs = crash_records(result, kind, count)
        if not recs:
            continue
        caps = [rollouts.capture(actor, result, r.initial_lane, r.episode) for r in recs]
        title = f"Crashes ({kind}): {label}, {result.unit}, the last {frames} steps"
        out[kind] = crash_strip(caps, frames, title, scale)
    return out
