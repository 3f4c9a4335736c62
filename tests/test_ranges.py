"""Every numeric key of every registered schema declares its range, and a value outside it
(NaN for floats; inf unless the range allows it) is refused at start in one line naming the key.

The walk reads the schemas from Hydra's ConfigStore (what :func:`memrl.configs.register_configs`
registers), so a new schema or a new numeric key cannot arrive unchecked: each registered schema
needs a place below (``PLACES``: the command whose start check reads it), and each int or float
field (``int | None``, ``list[float]``, ... included, nested schemas too) a range
(:func:`memrl.fields.spec`, the env's keys too). The
refusals run in-process, through each command's start check (``memrl.schemas.CHECKS``).
"""

from __future__ import annotations

import copy
import dataclasses
import math
import types
import typing
from functools import cache
from typing import Any

import pytest
from omegaconf import OmegaConf

from memrl.errors import USAGE_EXIT, exit_status, is_user_error, one_line
from memrl.fields import BOUNDS, RANGE_KEYS, nested_schemas

PLACES: dict[str, tuple[str, tuple[str, ...], str]] = {
    "env/lane_change_schema": ("train", (), "env."),
    "deploy/deploy_schema": ("deploy", (), "deploy."),
    "agent/dqn_schema": ("train", (), "agent."),
    "buffer/buffer_schema": ("train", (), "buffer."),
    "network/network_schema": ("train", (), "network."),
    "protocol/protocol_schema": ("evaluate", ("policy=scripted",), "protocol."),
    "eval_schema/base": ("train", (), "eval."),
    "mode_schema/default": ("train", (), "mode."),
    "mode_schema/A": ("train", ("+mode=A",), "mode."),
    "mode_schema/B": ("train", ("+mode=B",), "mode."),
    "mode_schema/R": ("train", ("+mode=R",), "mode."),
    "mode_schema/qdagger": ("train", ("+mode=qdagger",), "mode."),
    "mode_schema/jsrl": ("train", ("+mode=jsrl",), "mode."),
    "mode_schema/wsrl": ("train", ("+mode=wsrl",), "mode."),
}
"""Registered group schema -> (command, overrides, prefix of its keys) where its start check runs;
``<command>_schema`` is the command's own top level."""

EXTRA = {"report": ("runs=[.]",), "evaluate": ("policy=scripted",)}
"""Overrides a command's top level needs to get past its first refusal."""


def registered() -> dict[str, type]:
    from hydra.core.config_store import ConfigStore

    from memrl.configs import register_configs

    register_configs()
    out: dict[str, type] = {}

    def walk(repo: dict[str, Any], path: str) -> None:
        for name, item in repo.items():
            if isinstance(item, dict):
                if name != "hydra":
                    walk(item, f"{path}{name}/")
                continue
            schema = OmegaConf.get_type(item.node)
            if schema is not None and dataclasses.is_dataclass(schema):
                out[f"{path}{name.removesuffix('.yaml')}"] = schema

    walk(ConfigStore.instance().repo, "")
    return out


def numeric(typ: Any) -> tuple[type, bool] | None:
    """(int or float, is a list) for a numeric annotation (``int | None``, ``list[float]``)."""
    origin = typing.get_origin(typ)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(typ) if a is not type(None)]
        return numeric(args[0]) if len(args) == 1 else None
    if origin is list:
        inner = numeric(typing.get_args(typ)[0])
        return (inner[0], True) if inner and not inner[1] else None
    if typ in (int, float):
        return typ, False
    return None


def leaves(schema: type, prefix: str) -> list[tuple[str, dataclasses.Field, type, bool]]:
    """(dotted key, field, int or float, is a list) of every numeric field, nested ones included."""
    hints = typing.get_type_hints(schema)
    nested = nested_schemas(schema)
    out = []
    for f in dataclasses.fields(schema):
        if f.name in nested:
            out += leaves(nested[f.name], f"{prefix}{f.name}.")
        elif (kind := numeric(hints[f.name])) is not None:
            out.append((f"{prefix}{f.name}", f, *kind))
    return out


class Leaf(typing.NamedTuple):
    command: str
    overrides: tuple[str, ...]
    key: str
    field: dataclasses.Field
    kind: type
    is_list: bool
    env: bool
    """A key of the env schema (its messages name the key without ``env.``)."""


@cache
def every_leaf() -> list[Leaf]:
    """Every numeric key of every registered schema, where its start check runs."""
    from memrl.schemas import SCHEMAS

    out = []
    for name, schema in registered().items():
        command = name.removesuffix("_schema")
        if command in SCHEMAS and SCHEMAS[command] is schema:
            place = (command, EXTRA.get(command, ()), "")
        else:
            assert name in PLACES, f"registered schema {name} ({schema.__name__}) has no place in PLACES"
            place = PLACES[name]
        for key, f, kind, is_list in leaves(schema, place[2]):
            out.append(Leaf(place[0], place[1], key, f, kind, is_list, name == "env/lane_change_schema"))
    return out


def outside(leaf: Leaf) -> list[Any]:
    """Values the declared range refuses."""
    meta, kind = leaf.field.metadata, leaf.kind
    bad: list[Any] = []
    if "ge" in meta:
        bad.append(kind(meta["ge"] - 1))
    if "gt" in meta:
        bad.append(kind(meta["gt"]))
    if "le" in meta:
        bad.append(kind(meta["le"] + 1))
    if "lt" in meta:
        bad.append(kind(meta["lt"]))
    if kind is float:
        bad.append(math.nan)
        if not meta.get("inf"):
            bad.append(math.inf)
    return bad


def test_every_registered_schema_is_walked():
    names = set(registered())
    assert {"train_schema", "deploy/deploy_schema", "mode_schema/B", "env/lane_change_schema"} <= names
    keys = {leaf.key for leaf in every_leaf()}
    for key in ("agent.grad_clip", "mode.stage1.margin", "mode.stage1.plateau_checks",
                "mode.stage1.plateau_tol", "deploy.speed_pid.p", "deploy.curvature_pid.d",
                "protocol.duration", "mode.example.action_noise", "learner.seconds", "env.bev.path_time",
                "buffer.capacity"):
        assert key in keys, key
    assert len(every_leaf()) > 200


@pytest.mark.parametrize("leaf", every_leaf(), ids=lambda leaf: f"{leaf.command}:{leaf.key}")
def test_every_numeric_key_declares_a_range(leaf):
    command, key, f, kind = leaf.command, leaf.key, leaf.field, leaf.kind
    assert set(f.metadata) & set(RANGE_KEYS), f"{command} {key}: no range (memrl.fields.spec)"
    if kind is float and not f.metadata.get("finite"):
        assert set(f.metadata) & set(BOUNDS), f"{key}: give bounds, or finite=True"


@cache
def composed(command: str, overrides: tuple[str, ...]):
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from tests.conftest import CONF_DIR

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name=command, overrides=list(overrides))


def test_the_defaults_pass_every_start_check(tmp_path, monkeypatch):
    """The baseline of the walk below: each place's composed defaults are accepted."""
    from memrl.schemas import CHECKS

    monkeypatch.setenv("MEMRL_ROOT", str(tmp_path))
    monkeypatch.chdir(tmp_path)
    for command, overrides in {(leaf.command, leaf.overrides) for leaf in every_leaf()}:
        CHECKS[command](copy.deepcopy(composed(command, overrides)))


@pytest.mark.parametrize("leaf", every_leaf(), ids=lambda leaf: f"{leaf.command}:{leaf.key}")
def test_a_value_outside_the_range_is_refused_naming_the_key(leaf, tmp_path, monkeypatch):
    from memrl.schemas import CHECKS

    command, overrides, key, is_list = leaf.command, leaf.overrides, leaf.key, leaf.is_list
    monkeypatch.setenv("MEMRL_ROOT", str(tmp_path))
    monkeypatch.chdir(tmp_path)
    name = key.removeprefix("env.") if leaf.env else key  # the env's own messages
    for value in outside(leaf):
        cfg = copy.deepcopy(composed(command, overrides))
        given = value if (is_list and isinstance(value, list)) else ([value] if is_list else value)
        OmegaConf.update(cfg, key, given, merge=False)
        with pytest.raises(Exception) as info:
            CHECKS[command](cfg)
        err = info.value
        assert is_user_error(err) and exit_status(err) == USAGE_EXIT, f"{key}={given}: {err!r}"
        message = one_line(err)
        assert "\n" not in message and f"'{name}'" in message, f"{key}={given}: {message}"
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_nan_never_passes_and_inf_only_where_the_range_says_so():
    from dataclasses import dataclass

    from memrl.errors import ConfigError
    from memrl.fields import check_fields, spec

    @dataclass
    class Toy:
        limit: float = spec(1.0, gt=0, inf=True)
        weight: float = spec(1.0, finite=True)
        share: float = spec(0.5, ge=0, le=1)

    check_fields(Toy, {"limit": math.inf, "weight": -3.0, "share": 1.0})
    for key, value, said in (("limit", math.nan, "must be > 0 and inf allowed, got nan"),
                             ("weight", math.inf, "must be a finite number, got inf"),
                             ("weight", math.nan, "must be a finite number, got nan"),
                             ("share", math.nan, "must be in [0, 1], got nan")):
        with pytest.raises(ConfigError) as info:
            check_fields(Toy, {key: value}, "toy.")
        assert str(info.value) == f"config 'toy.{key}': {said}"
