"""memrl: memory reinforcement learning (double DQN with prior knowledge) on TorchRL."""

__version__ = "0.1.0"
