"""A faulty TCU for the example suite (``scenarios/suites/test_their_tcu.toml``): it speaks ``their.dbc``
and commands the driver's demand whatever the wheel does, so it keeps the demand through a slip.
It answers every reading at once: it fails ADH-1 (macro-slip) and ADH-2 (adhesion used) and no other.

    python scenarios/suites/faulty_tcus/keeps_demand.py --bus localbus:/run/user/1000/hil-bus-x
"""
import argparse
import signal
import sys
from pathlib import Path

import can
import cantools

from hil.bus.link import open_bus, resolve

DBC = Path(__file__).resolve().parent.parent / "their.dbc"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--bus", required=True, help="the plant's bus (as hil run --bus)")
    args = p.parse_args()
    db = cantools.database.load_file(str(DBC))
    notch, sensors, cmd = (db.get_message_by_name(n) for n in ("Notch", "Sensors", "TcuCmd"))
    handle = open_bus(resolve(args.bus))
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    demand_nm = 0.0
    try:
        while True:
            msg = handle.bus.recv(timeout=1.0)
            if msg is None or msg.is_extended_id:
                continue
            if msg.arbitration_id == notch.frame_id:
                demand_nm = notch.decode(bytes(msg.data))["DemandTorque"]
            elif msg.arbitration_id == sensors.frame_id:        # a reading: the demand, unchanged
                data = cmd.encode({"TorqueRequest": demand_nm, "SlipActive": 0, "MuEstimate": 0})
                handle.bus.send(can.Message(arbitration_id=cmd.frame_id, data=data, is_extended_id=False))
    finally:
        handle.close()


if __name__ == "__main__":
    sys.exit(main())
