"""Progress bars that draw only on a terminal.

A bar's redraws are carriage returns: in a log file or a CI log they become hundreds of lines.
Off a terminal the bar is not drawn, and the periodic log lines take its place (``train.log``
and the console get a line every ``log_every`` updates, as with ``progress=false``).
"""

from __future__ import annotations

import sys
from typing import Any

from tqdm import tqdm


def drawn(enabled: bool) -> bool:
    """Whether a bar asked for (``enabled``) is drawn: only when stderr is a terminal."""
    return bool(enabled) and sys.stderr is not None and sys.stderr.isatty()


def progress_bar(enabled: bool, **kwargs: Any) -> tqdm:
    """A tqdm bar on stderr if :func:`drawn`, else a silent one that still counts."""
    return tqdm(disable=not drawn(enabled), dynamic_ncols=True, **kwargs)
