"""Unknown keys of the typed config nodes, refused by name with the nearest known key.

Every node that a schema dataclass types (the command's top level, ``env``, ``agent``,
``buffer``, ``network``, ``mode``, ``eval``, ``protocol``, ...) is closed: its keys are the
schema's fields. Hydra refuses an unknown key without ``+`` (with a hint to add ``+``), but
composes one with ``+`` (``+agent.lrr=1``, ``+foo=bar``) into the config, where nothing reads
it. :func:`check_known_keys` refuses those; :func:`explain_unknown_key` words Hydra's own
refusal alike. Nodes typed ``Any`` or ``dict`` (``logger``, ``paths``, ``mode.example.env``)
stay open. Imports neither torch nor other memrl modules but :mod:`memrl.errors`.
"""

from __future__ import annotations

import dataclasses
import difflib
import re
from collections.abc import Iterator
from typing import Any

from omegaconf import DictConfig

from memrl.errors import EXPLAINERS, config_error

OWN_KEYS = ("hydra",)
"""Top-level keys that Hydra adds to every composed config (the callbacks see them)."""


def schema_fields(node: DictConfig) -> list[str] | None:
    """The keys the schema typing ``node`` declares (None: an open node)."""
    schema = node._metadata.object_type
    if schema is None or not dataclasses.is_dataclass(schema):
        return None
    return [f.name for f in dataclasses.fields(schema)]


def hint(key: str, known: list[str], prefix: str = "") -> str:
    """``did you mean '<prefix><nearest>'?`` (difflib), or the known keys when none is near."""
    close = difflib.get_close_matches(key, known, n=1)
    if close:
        return f"did you mean '{prefix}{close[0]}'?"
    return f"the keys here: {', '.join(sorted(known))}"


def unknown_keys(node: DictConfig, prefix: str = "") -> Iterator[tuple[str, str]]:
    """(dotted key, hint) of every key of a typed node that its schema lacks, depth first."""
    known = schema_fields(node)
    for key in node.keys():
        name = str(key)
        if not prefix and name in OWN_KEYS:
            continue
        if known is not None and name not in known:
            yield f"{prefix}{name}", hint(name, known, prefix)
            continue
        child = node._get_node(name)
        if isinstance(child, DictConfig) and not (child._is_none() or child._is_missing()
                                                  or child._is_interpolation()):
            yield from unknown_keys(child, f"{prefix}{name}.")


def check_known_keys(cfg: DictConfig) -> None:
    """Refuse the first key of a typed node that its schema lacks (added with ``+``).

    Raises:
        ConfigError: ``config 'agent.lrr': no such key (did you mean 'agent.lr'?)``.
    """
    if not isinstance(cfg, DictConfig):  # plain values of a Python caller: no schema to ask
        return
    for key, why in unknown_keys(cfg):
        raise config_error(key, f"no such key ({why})")


def explain_unknown_key(err: BaseException) -> str | None:
    """One line for Hydra's refusal of an unknown key without ``+`` (``agent.lrr=1``): the
    nearest known key instead of the hint to add ``+``. Hooked into
    :func:`memrl.errors.one_line`; None for any other error."""
    m = re.match(r"Could not override '([^']+)'", str(err))
    cause: Any = err.__cause__
    schema = getattr(cause, "object_type", None)
    if m is None or schema is None or not dataclasses.is_dataclass(schema):
        return None
    key = m.group(1)
    if str(getattr(cause, "full_key", "")) != key:  # a node on the way is missing (another mode's)
        return None
    parent, _, name = key.rpartition(".")
    known = [f.name for f in dataclasses.fields(schema)]
    if name in known:
        return None
    return f"config '{key}': no such key ({hint(name, known, f'{parent}.' if parent else '')})"


EXPLAINERS.append(explain_unknown_key)
