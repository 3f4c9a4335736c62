"""Typed config fields with their valid ranges (:func:`spec`) and the check of a node against
them (:func:`check_fields`); shared by every schema. Imports neither torch nor other memrl
modules, so any schema module can use it."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import field
from typing import Any

from omegaconf import MISSING, DictConfig, ListConfig, OmegaConf

from memrl.errors import config_error

SEED_MAX = 2**32 - 1
"""numpy seeds are 32-bit unsigned."""


def spec(default: Any = MISSING, *, ge: float | None = None, gt: float | None = None,
         le: float | None = None, lt: float | None = None, choices: tuple | None = None,
         nonempty: bool = False) -> Any:
    """A dataclass field with its valid range (for lists: of every element)."""
    meta = {k: v for k, v in dict(ge=ge, gt=gt, le=le, lt=lt, choices=choices,
                                  nonempty=nonempty).items() if v is not None and v is not False}
    if isinstance(default, list):
        return field(default_factory=lambda: list(default), metadata=meta)
    return field(default=default, metadata=meta)


def _valid(meta: Mapping[str, Any]) -> str:
    parts = [f"{op} {meta[k]}" for k, op in (("ge", ">="), ("gt", ">"), ("le", "<="), ("lt", "<"))
             if k in meta]
    if "choices" in meta:
        parts.append("one of " + ", ".join(map(str, meta["choices"])))
    return " and ".join(parts)


def _element_ok(value: Any, meta: Mapping[str, Any]) -> bool:
    if not meta:
        return True
    if "choices" in meta:
        return value in meta["choices"]
    if isinstance(value, bool) or not isinstance(value, int | float):
        return False
    return all(((k != "ge" or value >= meta[k]) and (k != "gt" or value > meta[k])
                and (k != "le" or value <= meta[k]) and (k != "lt" or value < meta[k]))
               for k in meta)


def check_fields(schema: type, node: Mapping[str, Any] | DictConfig, prefix: str = "") -> None:
    """Check every field of ``schema`` that declares a range, and nested schemas' fields.

    Raises:
        ConfigError: ``config '<key>': must be <range>, got <value>``.
    """
    for f in dataclasses.fields(schema):
        if f.name not in node:
            continue
        key = prefix + f.name
        sub = f.default_factory if f.default_factory is not dataclasses.MISSING else None
        meta = f.metadata
        if not meta and not dataclasses.is_dataclass(sub):
            continue  # nothing to check (and group nodes may hold Hydra interpolations)
        value = node[f.name]
        if isinstance(value, DictConfig | ListConfig):
            value = OmegaConf.to_container(value, resolve=True)
        if dataclasses.is_dataclass(sub) and isinstance(value, Mapping):
            check_fields(sub, value, key + ".")  # type: ignore[arg-type]
            continue
        if value is None:
            continue
        if isinstance(value, list):
            if meta.get("nonempty") and not value:
                raise config_error(key, "needs at least one value")
            bad = [v for v in value if not _element_ok(v, {k: m for k, m in meta.items()
                                                            if k != "nonempty"})]
            if bad:
                raise config_error(key, f"every value must be {_valid(meta)}, got {value!r}")
        elif {k for k in meta if k != "nonempty"} and \
                not _element_ok(value, {k: m for k, m in meta.items() if k != "nonempty"}):
            raise config_error(key, f"must be {_valid(meta)}, got {value!r}")
