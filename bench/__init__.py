"""Benchmarks and figure scripts (not installed): run from the repository root as modules,
e.g. `python -m bench.speed.train_speed`; README.md in this folder lists them."""
