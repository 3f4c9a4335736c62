"""Table III rows are whole configurations.

Evaluations of trained runs share a row only when the runs' saved ``config.yaml`` agree in
every key but the seed and the keys that cannot change what was learned (output paths,
logging, progress bars, resuming; :data:`IGNORED_KEYS`, ``report.row_ignore``). Runs of one
label (Default, A, B, ...) that differ elsewhere are separate rows, labelled by what differs:
``Default (total_frames=12000)`` and ``Default (total_frames=20000)``. Evaluations of other
policies (scripted, random, a person) are grouped by their label.

Every unit of a row must be evaluated once: a run evaluated twice, or two evaluations of the
same unit (seed, person) under the same configuration, stop the report naming the folders.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from memrl.errors import load_run_config
from memrl.evaluation.results import EvalResult
from memrl.modes import used

IGNORED_KEYS = ("seed", "progress", "resume", "paths", "logger", "log_every", "checkpoint_every",
                "hydra", "task_name", "debug", "variant", "mode.stage1.init", "eval", "seeds_engine")
"""Config keys (and key prefixes: ``paths`` covers ``paths.*``) that never split a row (a
study variant is in the row's name already: :func:`row_label`; ``mode.stage1.init`` names
each seed's own stage-1 run, e.g. ``.../B_constant_s${seed}``; ``eval``, the periodic
evaluation, trains the same weights whatever its schedule, and so does ``seeds_engine``)."""
ROW_ORDER = ("Default", "A", "B", "scripted", "random", "human")
"""Rows in this order first (each followed by its other-traffic rows, ``B (mixed)``); other
labels follow alphabetically."""
_ABSENT = "<absent>"


def row_label(mode: str, traffic: str = "constant", variant: str | None = None) -> str:
    """Row label of trained runs: the mode (Default, A, B), then the study variant and the
    traffic trained among when it is not constant-speed cars: ``B``, ``B (mixed)``, ``B (cue)``,
    ``B (cue, mixed)``."""
    extra = [p for p in (variant, None if traffic == "constant" else traffic) if p]
    return mode + (f" ({', '.join(extra)})" if extra else "")


@dataclass
class RowGroup:
    """The evaluations of one row."""

    label: str
    """Row label: the evaluations' name, plus what differs from other rows of that name."""
    base: str
    """The evaluations' name (Default, A, B, scripted, ...)."""
    results: list[EvalResult]
    settings: dict[str, Any] = field(default_factory=dict)
    """The runs' flattened config (ignored keys left out); {} for policies that are not runs."""
    variant: dict[str, Any] = field(default_factory=dict)
    """The keys in ``label``: where this row's config differs from other rows of ``base``."""


def run_folder(result: EvalResult) -> Path | None:
    """The training run an evaluation is of (None: not a trained run)."""
    if result.meta.get("kind") != "checkpoint":
        return None
    run = result.meta.get("run")
    return Path(run).resolve() if run else result.path.parent.resolve()


def flatten(tree: Any, prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` (lists stay values)."""
    if not isinstance(tree, dict):
        return {prefix: tree}
    out: dict[str, Any] = {}
    for key, value in tree.items():
        out.update(flatten(value, f"{prefix}{key}." if isinstance(value, dict) else f"{prefix}{key}"))
    return out


def is_ignored(key: str, ignore: Iterable[str]) -> bool:
    """``key`` is one of ``ignore`` or below one of them (``paths.output_dir`` below ``paths``)."""
    return any(key == p or key.startswith(p + ".") for p in ignore)


def run_settings(result: EvalResult, ignore: Sequence[str] = IGNORED_KEYS) -> dict[str, Any]:
    """The flattened ``config.yaml`` of the evaluated run without the ignored keys ({} when
    the evaluation is not of a run or the run has no config)."""
    run = run_folder(result)
    if run is None:
        return {}
    # the run as evaluated, else the folder holding the evaluation (a study moved elsewhere)
    found = [p for p in (run, result.path.parent) if (p / "config.yaml").is_file()]
    if not found:
        return {}
    tree = OmegaConf.to_container(load_run_config(found[0] / "config.yaml"), resolve=False)
    if isinstance(tree, dict):  # keys the run never read (Default: mode.*) split no row
        tree = used({str(k): v for k, v in tree.items()})
    return {k: v for k, v in flatten(tree).items() if not is_ignored(k, ignore)}


def check_duplicates(results: Sequence[EvalResult]) -> None:
    """Refuse a run evaluated more than once (one line naming the run and both evaluations)."""
    seen: dict[Path, Path] = {}
    for r in results:
        run = run_folder(r)
        if run is None:
            continue
        if run in seen:
            raise ValueError(f"report: run {run} was evaluated twice ({seen[run]} and {r.path}); "
                             "remove one evaluation or leave its folder out of 'runs'")
        seen[run] = r.path


def _check_units(group: RowGroup) -> None:
    seen: dict[str, Path] = {}
    for r in group.results:
        if r.unit in seen:
            raise ValueError(f"report: row '{group.label}' has two evaluations of {r.unit} with the same "
                             f"configuration ({seen[r.unit]} and {r.path}); keep one")
        seen[r.unit] = r.path


def _text(value: Any) -> str:
    return json.dumps(value) if not isinstance(value, str) else value


def _variant_key(variant: dict[str, Any]) -> tuple:
    """Sort key of a row's variant: numbers by value, then text."""
    return tuple((0, v, "") if isinstance(v, int | float) and not isinstance(v, bool) else (1, 0, _text(v))
                 for v in variant.values())


def _natural(text: str) -> tuple:
    """Sort key putting ``seed 2`` before ``seed 10``."""
    return tuple((0, int(t), "") if t.isdigit() else (1, 0, t) for t in text.replace("_", " ").split())


def row_rank(name: str) -> tuple[int, str]:
    """Sort key of a row name: :data:`ROW_ORDER`, ``B (mixed)`` right after ``B``, then the rest."""
    head = name.split(" (", 1)[0]
    return (ROW_ORDER.index(head) if head in ROW_ORDER else len(ROW_ORDER), name)


def split_rows(results: Sequence[EvalResult], ignore: Sequence[str] = IGNORED_KEYS) -> list[RowGroup]:
    """Rows of Table III: by name, then by configuration; units in natural order.

    Raises:
        ValueError: a run evaluated twice, or a unit twice in one row.
    """
    check_duplicates(results)
    by: dict[str, dict[str, tuple[dict[str, Any], list[EvalResult]]]] = {}
    for r in results:
        settings = run_settings(r, ignore)
        key = json.dumps(settings, sort_keys=True, default=str)
        by.setdefault(r.name, {}).setdefault(key, (settings, []))[1].append(r)
    groups = []
    for base in sorted(by, key=row_rank):
        configs = list(by[base].values())
        keys = sorted({k for s, _ in configs for k in s})
        differing = [k for k in keys if len({_text(s.get(k, _ABSENT)) for s, _ in configs}) > 1]
        rows = []
        for settings, rs in configs:
            variant = {k: settings.get(k, _ABSENT) for k in differing}
            label = base if not variant else base + " (" + ", ".join(
                f"{k}={_text(v)}" for k, v in variant.items()) + ")"
            rows.append(RowGroup(label, base, sorted(rs, key=lambda r: _natural(r.unit)), settings, variant))
        groups += sorted(rows, key=lambda g: _variant_key(g.variant))
    for g in groups:
        _check_units(g)
    return groups


def matching_rows(groups: Sequence[RowGroup], a: str, b: str) -> list[tuple[RowGroup, RowGroup]]:
    """The row pairs a comparison ``[a, b]`` names.

    ``a`` and ``b`` are row labels or names; a name stands for all its rows, and its rows are
    paired with those of the other side that agree on the keys its rows differ in (so
    ``B`` vs ``Default`` compares equal budgets when the budgets differ)."""
    def side(name: str) -> tuple[list[RowGroup], set[str]]:
        exact = [g for g in groups if g.label == name]
        if exact:
            return exact, set()
        rows = [g for g in groups if g.base == name]
        return rows, {k for g in rows for k in g.variant}

    rows_a, keys_a = side(a)
    rows_b, keys_b = side(b)
    keys = keys_a | keys_b
    return [(ga, gb) for ga in rows_a for gb in rows_b if ga is not gb
            and all(_text(ga.settings.get(k, _ABSENT)) == _text(gb.settings.get(k, _ABSENT)) for k in keys)]
