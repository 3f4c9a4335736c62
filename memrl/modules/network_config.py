"""Typed schema of the ``network`` config group (``conf/network/*.yaml``) and its check.

Imports no torch (``--help`` stays fast); :func:`check_network` imports the ``_target_``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from omegaconf import MISSING

from memrl.errors import config_error
from memrl.fields import check_fields, spec


@dataclass
class NetworkConfig:
    """The Q-network: a class (``_target_``) and its architecture arguments. The input (4
    stacked 84x84 gray frames) and the 9 actions come from the env, not from here."""

    _target_: str = MISSING
    """The network class, named by each ``conf/network/<name>.yaml``: ``memrl.modules.qnet.QNetwork``
    (Table I, ``network=table1``), ``memrl.modules.qnet.DuelingQNetwork`` (``network=dueling``),
    ``memrl.modules.categorical.CategoricalQNetwork`` (``network=c51``),
    ``memrl.modules.hlgauss.HLGaussQNetwork`` (``network=hlgauss``); any ``torch.nn.Module``
    taking ``channels, hidden, layernorm, layernorm_convs, pool_first`` keywords, whose keys
    of its own are those of the schema it names as ``config_schema`` (docs/network.md)."""
    channels: int = spec(16, ge=1)
    """Filters of each of the three 3x3 convs (Table I: 16)."""
    hidden: int = spec(256, ge=1)
    """Units of the hidden FC layer (Table I: 256; dueling: of each stream)."""
    layernorm: bool = False
    """LayerNorm after the hidden FC layer, before its ReLU (Table I: none)."""
    layernorm_convs: bool = False
    """LayerNorm over (channels, H, W) after each conv, before its pool and ReLU (``GroupNorm``
    with one group; Table I: none)."""


def check_network(node: Any, key: str = "network") -> None:
    """The ``network`` node against the schema of the class its ``_target_`` names (the
    class's ``config_schema``, :class:`NetworkConfig` where it names none): a ``_target_`` that
    is a ``torch.nn.Module`` class, each key known and of its type, each range, then the
    schema's own cross-key ``check``."""
    target = str(node.get("_target_") or "")  # missing: refused below as an empty name
    import logging

    from hydra.utils import get_class

    quiet = logging.getLogger("hydra.utils")  # get_class logs a line of its own before raising
    was, quiet.disabled = quiet.disabled, True
    try:
        cls = get_class(target)
    except Exception as err:  # ImportError, AttributeError, Hydra's own: one line naming the key
        raise config_error(f"{key}._target_", f"cannot import {target!r} "
                           f"({str(err).splitlines()[0] if str(err) else type(err).__name__})") from None
    finally:
        quiet.disabled = was
    import torch

    if not issubclass(cls, torch.nn.Module):
        raise config_error(f"{key}._target_", f"{target} is not a torch.nn.Module class")
    schema = network_schema(cls)
    check_typed(schema, node, key)
    check_fields(schema, node, f"{key}.")  # ranges, then the schema's own cross-key check


def network_schema(cls: type) -> type:
    """The schema of a network class: its ``config_schema``, else :class:`NetworkConfig`."""
    schema = getattr(cls, "config_schema", NetworkConfig)
    return schema if dataclasses.is_dataclass(schema) else NetworkConfig


def check_typed(schema: type, node: Any, key: str) -> None:
    """Every key of ``node`` is a field of ``schema`` and of its type (OmegaConf's structured
    merge), else one line naming the key."""
    from omegaconf import OmegaConf
    from omegaconf.errors import ConfigKeyError, OmegaConfBaseException

    plain = OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else dict(node)
    try:
        OmegaConf.merge(OmegaConf.structured(schema), plain)
    except OmegaConfBaseException as err:
        name = str(getattr(err, "full_key", "") or getattr(err, "key", "") or "")
        what = str(err).splitlines()[0]
        known = ", ".join(f.name for f in dataclasses.fields(schema) if f.name != "_target_")
        if isinstance(err, ConfigKeyError):  # a key the schema lacks
            raise config_error(f"{key}.{name}", f"{schema.__name__} has no such key (keys: {known})") \
                from None
        raise config_error(f"{key}.{name}", what) from None
