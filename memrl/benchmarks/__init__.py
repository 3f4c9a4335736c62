"""Benchmarks run by ``python -m memrl.bench``: each measures memrl beside a reference in one run."""
