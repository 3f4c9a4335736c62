"""Checkpoints: every file a run writes to be read again, and the one error they raise.

* :mod:`~memrl.checkpoint.weights`: the writer and reader of every ``.pt`` of weights
  (``final.pt``, ``stage1.pt``, pool snapshots), with its SHA-256.
* :mod:`~memrl.checkpoint.networks`: a run's Q-network (``final.pt``) and mode B's stage-1
  network (``stage1.pt``), built from the architecture the file stores.
* :mod:`~memrl.checkpoint.policy`: a trained Q-network as a policy (:func:`load_policy`).
* :mod:`~memrl.checkpoint.resume`: the resume checkpoint (``checkpoints/last/``): atomic save,
  its manifest, the config check on loading; what a run recorded of its config.
* :mod:`~memrl.checkpoint.opponents`: other cars driven by past runs' networks (the env's
  ``learned`` controller, registered with the env when this package is imported).
* :mod:`~memrl.checkpoint.errors`: :class:`CheckpointError`, for a file that is missing,
  damaged, of another kind or from another config.

Above the networks, data and modes (:mod:`memrl.modes`), below evaluation and training
(``tests/test_import_cycles.py`` holds the layer order).
"""

from __future__ import annotations

from memrl.checkpoint.errors import CheckpointError
from memrl.checkpoint.networks import (
    OFFLINE_WEIGHTS,
    check_stage1,
    describe,
    load_qnet,
    load_stage1_qnet,
    offline_state,
    qnet_from,
    qnet_weights,
    resolve,
    save_offline,
    save_qnet,
    stage1_file,
    stage1_source,
    stored_arch,
)
from memrl.checkpoint.opponents import LearnedCarController, OpponentPoolError
from memrl.checkpoint.policy import GreedyQPolicy, load_policy
from memrl.checkpoint.resume import recorded_config
from memrl.checkpoint.weights import CHECKSUM_KEY, load_weights, save_weights

__all__ = ["CHECKSUM_KEY", "CheckpointError", "GreedyQPolicy", "LearnedCarController", "OFFLINE_WEIGHTS",
           "OpponentPoolError", "check_stage1", "describe", "load_policy", "load_qnet", "load_stage1_qnet",
           "load_weights", "offline_state", "qnet_from", "qnet_weights", "recorded_config", "resolve",
           "save_offline", "save_qnet", "save_weights", "stage1_file", "stage1_source", "stored_arch"]
