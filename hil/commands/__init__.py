"""Sub-commands of ``hil``: one module each, each with ``register(subparsers)``."""
