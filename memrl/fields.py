"""Typed config fields with their valid ranges (:func:`spec`) and the check of a node against
them (:func:`check_fields`); shared by every schema. Imports neither torch nor other memrl
modules, so any schema module can use it."""

from __future__ import annotations

import dataclasses
import inspect
import math
from collections.abc import Mapping
from dataclasses import field
from functools import cache
from typing import Any, get_type_hints

from omegaconf import MISSING, DictConfig, ListConfig, OmegaConf

from memrl.errors import config_error

SEED_MAX = 2**32 - 1
"""numpy seeds are 32-bit unsigned."""


def spec(default: Any = MISSING, *, ge: float | None = None, gt: float | None = None,
         le: float | None = None, lt: float | None = None, choices: tuple | None = None,
         nonempty: bool = False, finite: bool = False, inf: bool = False) -> Any:
    """A dataclass field with its valid range (for lists: of every element).

    A number must be finite (NaN never passes; ``inf=True``: ``inf`` passes the bounds where
    it means something, e.g. "no limit"); ``finite=True`` alone says just that (any finite
    number, e.g. a reward weight or a bias).
    """
    meta = {k: v for k, v in dict(ge=ge, gt=gt, le=le, lt=lt, choices=choices, nonempty=nonempty,
                                  finite=finite, inf=inf).items()
            if v is not None and v is not False}
    if isinstance(default, list):
        return field(default_factory=lambda: list(default), metadata=meta)
    return field(default=default, metadata=meta)


BOUNDS = ("ge", "gt", "le", "lt")
RANGE_KEYS = (*BOUNDS, "choices", "finite")
"""Metadata keys that declare a range (a numeric field without one is refused by the tests)."""


def _valid(meta: Mapping[str, Any]) -> str:
    low = [(k, meta[k]) for k in ("ge", "gt") if k in meta]
    high = [(k, meta[k]) for k in ("le", "lt") if k in meta]
    parts = []
    if len(low) == 1 and len(high) == 1:
        (lk, lo), (hk, hi) = low[0], high[0]
        parts.append(f"in {'[' if lk == 'ge' else '('}{lo}, {hi}{']' if hk == 'le' else ')'}")
    else:
        parts += [f"{op} {meta[k]}" for k, op in (("ge", ">="), ("gt", ">"), ("le", "<="),
                                                   ("lt", "<")) if k in meta]
    if "choices" in meta:
        parts.append("one of " + ", ".join(map(str, meta["choices"])))
    if not parts and meta.get("finite"):
        parts.append("a finite number")
    if meta.get("inf"):
        parts.append("inf allowed")
    return " and ".join(parts)


def _element_ok(value: Any, meta: Mapping[str, Any]) -> bool:
    if not meta:
        return True
    if "choices" in meta:
        return value in meta["choices"]
    if isinstance(value, bool) or not isinstance(value, int | float):
        return False
    if isinstance(value, float) and (math.isnan(value) or (math.isinf(value) and not meta.get("inf"))):
        return False
    return all(((k != "ge" or value >= meta[k]) and (k != "gt" or value > meta[k])
                and (k != "le" or value <= meta[k]) and (k != "lt" or value < meta[k]))
               for k in meta)


@cache
def nested_schemas(schema: type) -> dict[str, type]:
    """Field name -> the dataclass schema that types it (its annotation, else its default
    factory's class: a lambda building a dataclass counts)."""
    try:
        hints = get_type_hints(schema)
    except Exception:  # an annotation that does not resolve: fall back to the factories
        hints = {}
    out: dict[str, type] = {}
    for f in dataclasses.fields(schema):
        typ = hints.get(f.name)
        if isinstance(typ, type) and dataclasses.is_dataclass(typ):
            out[f.name] = typ
        elif f.default_factory is not dataclasses.MISSING and dataclasses.is_dataclass(f.default_factory):
            out[f.name] = f.default_factory  # type: ignore[assignment]
    return out


@cache
def integral_fields(schema: type) -> frozenset[str]:
    """Fields of ``schema`` typed ``int`` (or ``int | None``): a value there must be an int,
    not a float or a bool, where the node was not typed by the schema (a plain dict)."""
    try:
        hints = get_type_hints(schema)
    except Exception:  # an annotation that does not resolve: no such check
        return frozenset()
    return frozenset(name for name, typ in hints.items() if typ is int or typ == int | None)


def _check_value(key: str, value: Any, meta: Mapping[str, Any], integral: bool, optional: bool) -> None:
    """One value against its field's range (``integral``: its field is typed ``int``)."""
    bare = {k: m for k, m in meta.items() if k != "nonempty"}
    if isinstance(value, list):
        if meta.get("nonempty") and not value:
            raise config_error(key, "needs at least one value")
        if any(not _element_ok(v, bare) for v in value):
            raise config_error(key, f"every value must be {_valid(meta)}, got {value!r}")
    elif integral and set(meta) & set(BOUNDS) and (isinstance(value, bool) or not isinstance(value, int)):
        raise config_error(key, f"must be an int {_valid(meta)}, got {value!r}")
    elif bare and not _element_ok(value, bare):
        null = " or null" if optional else ""  # an optional key (``int | None``)
        raise config_error(key, f"must be {_valid(meta)}{null}, got {value!r}")


def check_fields(schema: type, node: Mapping[str, Any] | DictConfig, prefix: str = "") -> None:
    """Check every field of ``schema`` that declares a range, nested schemas' fields, then the
    schema's own cross-key rule: the one way a value is checked.

    A schema states its ranges on its fields (:func:`spec`) and its rules across keys in one
    static method ``check(node, prefix)`` (keys that must fit together, or a choice another
    key restricts), raising :func:`memrl.errors.config_error` naming the key; it runs after
    every key's range has passed, nested schemas' rules before their parent's.

    Raises:
        ConfigError: ``config '<key>': must be <range>, got <value>``.
    """
    nested = nested_schemas(schema)
    for f in dataclasses.fields(schema):
        if f.name not in node:
            continue
        key = prefix + f.name
        sub = nested.get(f.name)
        meta = {k: v for k, v in f.metadata.items() if k in RANGE_KEYS or k in ("nonempty", "inf")}
        if not meta and sub is None:
            continue  # nothing to check (and group nodes may hold Hydra interpolations)
        value = node[f.name]
        if isinstance(value, DictConfig | ListConfig):
            value = OmegaConf.to_container(value, resolve=True)
        if sub is not None and isinstance(value, Mapping):
            check_fields(sub, value, key + ".")  # type: ignore[arg-type]
            continue
        if value is not None:
            _check_value(key, value, meta, integral=f.name in integral_fields(schema),
                         optional="None" in str(f.type))
    rule = inspect.getattr_static(schema, "check", None)  # a static method (a field may be named check)
    if isinstance(rule, staticmethod):  # the rule reads keys as attributes or with .get()
        rule.__func__(node if isinstance(node, DictConfig) else OmegaConf.create(dict(node)), prefix)
