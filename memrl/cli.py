"""Command-line helpers shared by the ``@hydra.main`` entry points."""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from typing import Any

_FLAGS_FIRST = ("-m", "--multirun")


def normalize_argv(argv: Sequence[str], positional_key: str | None = None) -> list[str]:
    """Let users put Hydra's flags anywhere and name sub-commands by bare words.

    Plain Hydra rejects ``-m`` after an override (``python -m memrl.train +mode=B -m seed=0,1``);
    this moves ``-m``/``--multirun`` to the front. Bare words (no ``=``, not a flag) become
    ``positional_key=[word, ...]`` when a key is given, e.g. ``bench env`` -> ``benchmarks=[env]``.
    """
    args = list(argv)
    flags = [a for a in args if a in _FLAGS_FIRST]
    rest = [a for a in args if a not in _FLAGS_FIRST]
    words: list[str] = []
    if positional_key is not None:
        # A bare word directly after a flag that takes a value is that flag's value.
        takes_value = {"--config-name", "-cn", "--config-path", "-cp", "--config-dir", "-cd",
                       "--info", "-i", "--package", "-p", "--experimental-rerun"}
        kept: list[str] = []
        for i, a in enumerate(rest):
            prev = rest[i - 1] if i else ""
            if "=" not in a and not a.startswith("-") and prev not in takes_value:
                words.append(a)
            else:
                kept.append(a)
        rest = kept
    if words:
        rest.append(f"{positional_key}=[{','.join(words)}]")
    return flags + rest


def run_hydra(main: Callable[[], Any], positional_key: str | None = None) -> Any:
    """Call a ``@hydra.main`` function after :func:`normalize_argv` on ``sys.argv``."""
    sys.argv = [sys.argv[0], *normalize_argv(sys.argv[1:], positional_key)]
    return main()
