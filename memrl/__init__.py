"""memrl: memory reinforcement learning (double DQN with prior knowledge) on TorchRL."""

from pathlib import Path

__version__ = "0.1.0"

CONF_DIR = Path(__file__).parent / "conf"
"""The Hydra configs: ``memrl/conf``, a link to the checkout's top-level ``conf/`` that the build
copies into the wheel (``pyproject.toml``'s package data), so installed and editable memrl read
the same files."""
