"""Structured-config schemas registered with Hydra's ConfigStore."""

from __future__ import annotations

from hydra.core.config_store import ConfigStore

from memrl.control.config import DeployConfig
from memrl.envs.config import LaneChangeConfig


def register_configs() -> None:
    """Register the typed schemas that the YAML groups extend (idempotent)."""
    cs = ConfigStore.instance()
    cs.store(group="env", name="lane_change_schema", node=LaneChangeConfig)
    cs.store(group="deploy", name="deploy_schema", node=DeployConfig)
