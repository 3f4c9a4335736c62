"""The error of every checkpoint file: missing, damaged, of another kind or from another config."""

from __future__ import annotations

from memrl.errors import UserError


class CheckpointError(UserError, ValueError):
    """A checkpoint is missing, corrupt or from another config."""
