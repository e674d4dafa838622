"""A TCU of another make with more frames than its command (tests/test_mapping.py, issue 49 item 7): it
speaks ``tests/data/their_with_status.dbc`` and, for each reading (the Sensors frame), first sends
TcuState (0x201: a temperature, 200 degC -- past its DBC maximum of 150 -- for the readings ``--hot``
names), every tenth reading TcuDiag (0x202) and every hundredth TcuVersion (0x310, in the DBC, not in
the mapping) and a frame of id 0x7FF (in no DBC), then TcuCmd (0x200) with the driver's demand.  On
SIGTERM it writes what it sent, by frame, to ``--report`` (JSON): the oracle of the plant's counts.

    python tests/data/status_tcu.py --bus localbus:DIR --report sent.json
"""
import argparse
import json
import signal
import sys
from pathlib import Path

import can
import cantools

from hil.bus.link import open_bus, resolve

DBC = Path(__file__).resolve().parent / "their_with_status.dbc"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--bus", required=True, help="the plant's bus (as hil run --bus)")
    p.add_argument("--report", required=True, help="JSON file: the frames sent, by name")
    p.add_argument("--hot", default="100:110", help="readings A:B whose TcuState says 200 degC")
    args = p.parse_args()
    hot = range(*map(int, args.hot.split(":")))
    db = cantools.database.load_file(str(DBC))
    notch, sensors, cmd, state, diag, version = (db.get_message_by_name(n) for n in (
        "Notch", "Sensors", "TcuCmd", "TcuState", "TcuDiag", "TcuVersion"))
    handle = open_bus(resolve(args.bus))
    sent = {"TcuCmd": 0, "TcuState": 0, "TcuState_hot": 0, "TcuDiag": 0, "TcuVersion": 0, "0x7FF": 0}

    def send(frame_id, data, what):
        handle.bus.send(can.Message(arbitration_id=frame_id, data=data, is_extended_id=False))
        sent[what] += 1

    def stop(*_):
        Path(args.report).write_text(json.dumps(sent))
        sys.exit(0)

    signal.signal(signal.SIGTERM, stop)
    demand_nm, n = 0.0, 0
    try:
        while True:
            msg = handle.bus.recv(timeout=1.0)
            if msg is None or msg.is_extended_id:
                continue
            if msg.arbitration_id == notch.frame_id:
                demand_nm = notch.decode(bytes(msg.data))["DemandTorque"]
            elif msg.arbitration_id == sensors.frame_id:
                # cantools refuses a value past the DBC's maximum: the hot temperature is encoded unchecked
                celsius = 200 if n in hot else 60
                send(state.frame_id, state.encode({"Temperature": celsius, "SlipStage": 0}, strict=False), "TcuState")
                sent["TcuState_hot"] += celsius > 150
                if n % 10 == 0:
                    send(diag.frame_id, diag.encode({"Counter": n // 10, "FaultCode": 0}), "TcuDiag")
                if n % 100 == 0:
                    send(version.frame_id, version.encode({"Build": 49}), "TcuVersion")
                    send(0x7FF, bytes(8), "0x7FF")
                send(cmd.frame_id, cmd.encode({"TorqueRequest": demand_nm, "SlipActive": 0, "MuEstimate": 0}), "TcuCmd")
                n += 1
    finally:
        handle.close()


if __name__ == "__main__":
    sys.exit(main())
