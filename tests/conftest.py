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


def _compose_train(overrides: list[str]) -> DictConfig:
    register_configs()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name="train", overrides=overrides, return_hydra_config=False)


@pytest.fixture(scope="session")
def smoke_run(tmp_path_factory) -> Path:
    """One finished 2-episode default-mode run for the whole session (copy it before changing
    anything in it): ``config.yaml``, ``checkpoints/last`` and ``final.pt``, ``summary.json``."""
    from memrl.train import train
    from tests.helpers import TINY

    run = tmp_path_factory.mktemp("smoke_run") / "run"
    train(_compose_train([*TINY, "total_episodes=2"]), run)
    return run


@pytest.fixture(scope="session")
def smoke_b_run(tmp_path_factory) -> Path:
    """One finished 2-episode mode B run (stage 1 on 120 demo transitions, then stage 2) for
    the whole session: ``checkpoints/stage1.pt`` beside the rest (copy it before changing it)."""
    from memrl.train import train
    from tests.helpers import make_demos, tiny

    run = tmp_path_factory.mktemp("smoke_b_run") / "run"
    train(_compose_train([*tiny("B"), "total_episodes=2"]), run, demos=make_demos(120))
    return run
