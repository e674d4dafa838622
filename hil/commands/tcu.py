"""``hil tcu SCENARIO --bus ...``: the identifier (TCU) alone on a bus, e.g. against a real rig or a plant
someone else runs.  It answers PlantSensor frames until the plant's heartbeat says the run finished;
a plant silent for longer than the limit ends it with exit code 3."""
from __future__ import annotations


def register(sub) -> None:
    from ..tcu_process import add_arguments

    p = sub.add_parser("tcu", help="run the identifier (TCU) alone on a bus")
    add_arguments(p)
    p.set_defaults(func=cmd_tcu)


def cmd_tcu(args) -> int:
    from ..bus import BusError
    from ..cli import UserError
    from ..tcu_process import run_tcu

    try:
        return run_tcu(args)
    except BusError as e:
        raise UserError(str(e)) from None
