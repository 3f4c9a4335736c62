"""Lane-change environment, its bird's-eye-view renderer and the TorchRL pipeline."""

from __future__ import annotations

from gymnasium.envs.registration import register, registry

ENV_ID = "memrl/LaneChange-v0"


def register_envs() -> None:
    """Register ``memrl/LaneChange-v0`` with gymnasium (idempotent)."""
    if ENV_ID not in registry:
        register(id=ENV_ID, entry_point="memrl.envs.lane_change:LaneChangeEnv",
                 vector_entry_point="memrl.envs.vector:LaneChangeVectorEnv")


register_envs()
