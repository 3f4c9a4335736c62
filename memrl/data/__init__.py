"""Prior-knowledge datasets and the replay buffers of each mode."""
