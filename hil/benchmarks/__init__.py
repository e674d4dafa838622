"""Benchmarks of ``hil bench``: one module each, each with ``register(subparsers)``."""
