"""An evaluation folder: ``eval.json`` (protocol, seeds, scores, crashes, who) and ``episodes.csv``."""

from __future__ import annotations

import csv
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from memrl.errors import UserError
from memrl.evaluation.crash_counts import by_lane as crashes_by_lane
from memrl.evaluation.protocol import (
    CSV_FIELDS,
    EpisodeRecord,
    ProtocolConfig,
    Score,
    protocol_id,
    record_from_row,
    scores_by_lane,
)

EVAL_JSON = "eval.json"
EPISODES_CSV = "episodes.csv"


@dataclass
class EvalResult:
    """The results of one policy (one row-unit of Table III: a training seed, a person, ...)."""

    name: str
    """Row label (Default, A, B, scripted, random, human, ...)."""
    unit: str
    """What distinguishes results of the same label (``seed 0``, a person, ...)."""
    scores: dict[str, Score]
    """Per initial-lane setting."""
    protocol: dict[str, Any]
    protocol_id: str
    seeds: list[int]
    """Scene seeds, episode i first (the same list for every initial-lane setting)."""
    path: Path
    """The evaluation folder."""
    meta: dict[str, Any] = field(default_factory=dict)
    stopped_early: bool = False
    wall_s: float = 0.0
    env: dict[str, Any] = field(default_factory=dict)
    """Env config of the episodes (the protocol's rules applied; ``initial_lane`` of the first
    setting): with ``meta`` and a seed, enough to replay an episode."""
    crash_sight: dict[str, Any] | None = None
    """Q against the return by steps before a crash and the action gaps, per initial-lane
    setting (:func:`memrl.evaluation.crash_sight.summarize`); None: not recorded (a policy
    without Q-values, or an evaluation made before they were recorded)."""

    def records(self) -> list[EpisodeRecord]:
        """The per-episode records from the folder's CSV."""
        with (self.path / EPISODES_CSV).open(newline="") as f:
            return [record_from_row(row) for row in csv.DictReader(f)]


def write_result(out_dir: Path, name: str, records: list[EpisodeRecord], protocol: ProtocolConfig,
                 seeds: list[int], meta: dict[str, Any], *, stopped_early: bool = False,
                 wall_s: float = 0.0, env: dict[str, Any] | None = None,
                 extra: dict[str, Any] | None = None,
                 crash_sight: dict[str, Any] | None = None) -> EvalResult:
    """Write ``episodes.csv`` and ``eval.json`` into ``out_dir`` (replacing earlier ones);
    ``crash_sight`` (when given) goes into ``eval.json`` under that key."""
    out_dir.mkdir(parents=True, exist_ok=True)
    with (out_dir / EPISODES_CSV).open("w", newline="") as f:
        writer = csv.DictWriter(f, CSV_FIELDS)
        writer.writeheader()
        writer.writerows(r.row() for r in records)
    result = EvalResult(name=name, unit=str(meta.get("unit", name)), scores=scores_by_lane(records),
                        protocol=asdict(protocol), protocol_id=protocol_id(protocol), seeds=list(seeds),
                        path=out_dir, meta=dict(meta), stopped_early=stopped_early, wall_s=wall_s,
                        env=dict(env or {}), crash_sight=crash_sight)
    doc = {
        "name": result.name, "unit": result.unit,
        "scores": {lane: asdict(s) for lane, s in result.scores.items()},
        "protocol": result.protocol, "protocol_id": result.protocol_id,
        "episodes_done": len(records), "stopped_early": stopped_early,
        "wall_s": round(wall_s, 3), "meta": result.meta, "env": result.env,
        "crashes": crashes_by_lane(records), **dict(extra or {}),
        **({"crash_sight": crash_sight} if crash_sight is not None else {}),
        "seeds": result.seeds,
    }
    tmp = out_dir / (EVAL_JSON + ".tmp")
    tmp.write_text(json.dumps(doc, indent=2))
    tmp.replace(out_dir / EVAL_JSON)  # eval.json last and whole: its presence means complete
    return result


def read_result(path: Path) -> EvalResult:
    """An evaluation folder (or its ``eval.json``) back as an :class:`EvalResult`."""
    folder = path.parent if path.name == EVAL_JSON else path
    file = folder / EVAL_JSON
    try:
        doc = json.loads(file.read_text())
        return _result_of(doc, folder)
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError, AttributeError) as err:
        why = f"no key {err}" if isinstance(err, KeyError) else str(err).splitlines()[0]
        raise EvalFileError(f"{file}: not an evaluation memrl can read ({why}); evaluate it again "
                            "(python -m memrl.evaluate) or remove the folder") from None


class EvalFileError(UserError, ValueError):
    """An ``eval.json`` that is garbled or lacks what an evaluation records."""


def _result_of(doc: Any, folder: Path) -> EvalResult:
    return EvalResult(name=doc["name"], unit=doc["unit"],
                      scores={k: Score(**v) for k, v in doc["scores"].items()},
                      protocol=doc["protocol"], protocol_id=doc["protocol_id"], seeds=doc["seeds"],
                      path=folder, meta=doc.get("meta", {}), stopped_early=doc.get("stopped_early", False),
                      wall_s=doc.get("wall_s", 0.0), env=doc.get("env", {}),
                      crash_sight=doc.get("crash_sight"))


def find_results(paths: list[str | Path]) -> list[EvalResult]:
    """Every evaluation folder (holding ``eval.json``) at or below the given folders."""
    found: list[Path] = []
    for item in paths:
        p = Path(item)
        if not p.exists():
            raise FileNotFoundError(f"report 'runs': no such folder {p}")
        found += [p] if (p / EVAL_JSON).is_file() else sorted(f.parent for f in p.glob(f"**/{EVAL_JSON}"))
    return [read_result(f) for f in dict.fromkeys(f.resolve() for f in found)]
