"""User errors: bad input that the command line reports as one line (exit code 2).

Config and data errors derive from :class:`UserError`; :func:`is_user_error` also recognises
Hydra's and OmegaConf's config errors, the demo loader's errors and file-system errors (a
missing or read-only path, a full disk). Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import errno
import sys
from typing import Any

USAGE_EXIT = 2
"""Exit status of a command refused for bad input (as argparse does)."""

ONE_LINE_ENV = "MEMRL_ONE_LINE_ERRORS"
"""Set by :func:`memrl.cli.run_hydra` while user errors are to be reported as one line."""

_FILE_ERRNOS = {errno.ENOSPC, errno.EROFS, errno.EACCES, errno.EPERM, errno.EDQUOT, errno.ENOENT,
                errno.EEXIST, errno.ENOTDIR, errno.EISDIR}
_NOISE = ("full_key:", "object_type=", "reference_type=", "msg:", "    ")


EXPLAINERS: list[Any] = []
"""Callables ``err -> str | None`` that word an error better than its own text (first one that
answers wins; :func:`memrl.modes.explain_key_error`, a key of a mode that is not selected)."""


class UserError(Exception):
    """Bad input (a config value, a file): the message names the key or file and what is valid."""


class ConfigError(UserError, ValueError):
    """A config value is out of range or of the wrong type; the message names the key."""


def config_error(key: str, message: str) -> ConfigError:
    """``config '<key>': <message>``, the one form of every range error."""
    return ConfigError(f"config '{key}': {message}")


def is_user_error(err: BaseException) -> bool:
    """Whether ``err`` is bad input (one line) rather than a bug (a traceback)."""
    if isinstance(err, UserError):
        return True
    demos = sys.modules.get("memrl.data.demos")  # loaded whenever its error can have happened
    if demos is not None and isinstance(err, getattr(demos, "DemoDatasetError", ())):
        return True
    omegaconf = sys.modules.get("omegaconf.errors")
    if omegaconf is not None and isinstance(err, omegaconf.OmegaConfBaseException):
        return True
    hydra_errors = sys.modules.get("hydra.errors")
    if hydra_errors is not None and isinstance(err, hydra_errors.HydraException):
        return True
    return isinstance(err, OSError) and err.errno in _FILE_ERRNOS


def exit_status(err: BaseException) -> int:
    """The command's exit status for an error: :data:`USAGE_EXIT` for bad input, else 1."""
    return USAGE_EXIT if is_user_error(err) else 1


def one_line(err: BaseException) -> str:
    """The message of a user error on one line, naming the key (config errors) or the file."""
    for explain in EXPLAINERS:
        text = explain(err)
        if text:
            return text
    omegaconf = sys.modules.get("omegaconf.errors")
    cause = err.__cause__
    if omegaconf is not None and isinstance(cause, omegaconf.OmegaConfBaseException) and \
            not isinstance(err, omegaconf.OmegaConfBaseException):
        # Hydra's "Error merging override x=y" wraps OmegaConf's error, which names the key.
        return f"{_first_lines(err)}: {one_line(cause)}"
    text = _first_lines(err)
    key = getattr(err, "full_key", None)
    if key and f"'{key}'" not in text and omegaconf is not None and \
            isinstance(err, omegaconf.OmegaConfBaseException):
        text = f"config '{key}': {text}"
    if isinstance(err, OSError) and err.filename is not None and str(err.filename) not in text:
        text = f"{err.filename}: {err.strerror or text}"
    return text


def _first_lines(err: BaseException) -> str:
    lines = [ln.strip() for ln in str(err).splitlines()
             if ln.strip() and not ln.startswith(_NOISE) and not ln.strip().startswith(_NOISE[:4])]
    return "; ".join(ln.rstrip(".:") for ln in lines) or type(err).__name__


def load_run_config(path: Any) -> Any:
    """``OmegaConf.load`` of a run's ``config.yaml``, refusing a garbled file by name (a YAML
    error, or a document that is not a mapping) instead of a parser traceback."""
    from omegaconf import DictConfig, OmegaConf

    try:
        loaded = OmegaConf.load(path)
    except Exception as err:  # yaml's scanner and parser errors, OmegaConf's own
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise UserError(f"{path}: unreadable run config ({first})") from None
    if not isinstance(loaded, DictConfig):
        raise UserError(f"{path}: unreadable run config (not a mapping of keys)")
    return loaded


def instantiate_checked(node: object) -> object:
    """Hydra's ``instantiate``, but a :class:`UserError` raised by the object's constructor
    comes out as itself (one line), not wrapped in Hydra's "Error in call to target ..."."""
    from hydra.utils import instantiate

    try:
        return instantiate(node)
    except Exception as err:
        if isinstance(err.__cause__, UserError):
            raise err.__cause__ from None
        raise
