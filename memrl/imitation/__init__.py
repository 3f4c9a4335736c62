"""Imitation of the scripted driver: DAgger with the expert on call (``python -m memrl.dagger``)."""
