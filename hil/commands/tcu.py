"""``hil tcu SCENARIO --bus ...``: the identifier (TCU) alone on a bus, e.g. against a real rig or a plant
someone else runs.  It answers PlantSensor frames until the plant's heartbeat says the run finished;
a plant silent for longer than the limit ends it with exit code 3, a plant that reports a fault with 4."""
from __future__ import annotations


def register(sub) -> None:
    from ..tcu_node import add_arguments

    p = sub.add_parser("tcu", help="run the identifier (TCU) alone on a bus")
    add_arguments(p)
    p.set_defaults(func=cmd_tcu)


def cmd_tcu(args) -> int:
    from ..tcu_node import run_tcu

    return run_tcu(args)
