"""Typed schema of the ``network`` config group (``conf/network/*.yaml``) and its check.

Imports no torch (``--help`` stays fast); :func:`check_network` imports the ``_target_``.
"""

from __future__ import annotations

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
    (Table I, ``network=table1``), ``memrl.modules.qnet.DuelingQNetwork`` (``network=dueling``);
    any ``torch.nn.Module`` taking ``channels, hidden, layernorm, layernorm_convs, pool_first``
    keywords (docs/network.md)."""
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
    """Ranges of the ``network`` node, and a ``_target_`` that names a ``torch.nn.Module`` class."""
    check_fields(NetworkConfig, node, f"{key}.")
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
