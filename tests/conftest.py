from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig

from memrl.configs import register_configs

CONF_DIR = str(Path(__file__).resolve().parents[1] / "conf")

os.environ.setdefault("SDL_VIDEODRIVER", "offscreen")


@pytest.fixture
def compose_cfg() -> Callable[..., DictConfig]:
    """Compose one of the real configs (``conf/<name>.yaml``) with overrides."""

    def _compose(name: str, overrides: list[str] | None = None) -> DictConfig:
        register_configs()
        GlobalHydra.instance().clear()
        with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
            return compose(config_name=name, overrides=overrides or [], return_hydra_config=False)

    return _compose


@pytest.fixture(scope="module")
def demos():
    """120 demo transitions recorded through the real TorchRL pipeline (one set per module)."""
    from tests.helpers import make_demos

    return make_demos(120)
