"""A TCU of another make that freezes (tests/test_mapping.py, issue 49 item 8): it speaks
``scenarios/suites/their.dbc``, commands the driver's demand for each reading, and after ``--after``
readings answers no more (it keeps the bus open and reads on: a frozen unit, not a dead process).

    python tests/data/freezes_tcu.py --bus localbus:DIR --after 300
"""
import argparse
import signal
import sys
from pathlib import Path

import can
import cantools

from hil.bus.link import open_bus, resolve

DBC = Path(__file__).resolve().parents[2] / "scenarios" / "suites" / "their.dbc"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--bus", required=True, help="the plant's bus (as hil run --bus)")
    p.add_argument("--after", type=int, default=300, help="readings answered before it freezes")
    args = p.parse_args()
    db = cantools.database.load_file(str(DBC))
    notch, sensors, cmd = (db.get_message_by_name(n) for n in ("Notch", "Sensors", "TcuCmd"))
    handle = open_bus(resolve(args.bus))
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    demand_nm, answered = 0.0, 0
    try:
        while True:
            msg = handle.bus.recv(timeout=1.0)
            if msg is None or msg.is_extended_id:
                continue
            if msg.arbitration_id == notch.frame_id:
                demand_nm = notch.decode(bytes(msg.data))["DemandTorque"]
            elif msg.arbitration_id == sensors.frame_id and answered < args.after:
                data = cmd.encode({"TorqueRequest": demand_nm, "SlipActive": 0, "MuEstimate": 0})
                handle.bus.send(can.Message(arbitration_id=cmd.frame_id, data=data, is_extended_id=False))
                answered += 1
    finally:
        handle.close()


if __name__ == "__main__":
    sys.exit(main())
