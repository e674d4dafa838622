"""A faulty TCU for the example suite (``scenarios/suites/test_their_tcu.toml``): it speaks ``their.dbc``
and runs the built-in TCU's identifier and control law (``identifier.TractionIdentifier``), but sends
each torque command ``LATE_S`` (five exchange periods) after the reading it answers, and answers the
newest reading then (the readings that came meanwhile are passed over), as a TCU whose control task
takes five periods would.

- Lockstep: the plant waits for each command, so it controls the wheel as the built-in TCU does: it
  fails TIM-1 (answers within three periods) and no other.
- Real time: its commands come after their periods' deadlines (four periods in five go unanswered):
  the run misses more deadlines than ``[bus] max_missed_fraction`` allows in periods the plant began
  on time, so the run fails as a whole, "the TCU's commands came late", every check with it
  (docs/guide/verdicts.md).

    python scenarios/suites/faulty_tcus/answers_late.py scenarios/wet_patch.toml --bus localbus:DIR
"""
import argparse
import signal
import sys
import time
from pathlib import Path

import can
import cantools

from hil.bus.link import open_bus, resolve
from hil.config import load_scenario
from identifier import DEFAULT_STRATEGY, TractionIdentifier
from identifier.messages import SensorReading

DBC = Path(__file__).resolve().parent.parent / "their.dbc"
LATE_S = 0.005


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scenario", help="the scenario (its vehicle, identifier and control law)")
    p.add_argument("--bus", required=True, help="the plant's bus (as hil run --bus)")
    args = p.parse_args()
    scenario = load_scenario(args.scenario)
    law = scenario.control.law
    tcu = TractionIdentifier(scenario.identifier_settings(), DEFAULT_STRATEGY, scenario.run.seed, law,
                             scenario.control.options.get(law))
    db = cantools.database.load_file(str(DBC))
    notch, sensors, cmd = (db.get_message_by_name(n) for n in ("Notch", "Sensors", "TcuCmd"))
    handle = open_bus(resolve(args.bus))
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    step = 0
    try:
        while True:
            msg = handle.bus.recv(timeout=1.0)
            if msg is None or msg.is_extended_id:
                continue
            if msg.arbitration_id == notch.frame_id:
                tcu.demand_nm = notch.decode(bytes(msg.data))["DemandTorque"]
            elif msg.arbitration_id == sensors.frame_id:
                v = sensors.decode(bytes(msg.data))
                while (newer := handle.bus.recv(timeout=0.0)) is not None:    # real time: readings came meanwhile
                    if newer.is_extended_id:
                        continue
                    if newer.arbitration_id == notch.frame_id:
                        tcu.demand_nm = notch.decode(bytes(newer.data))["DemandTorque"]
                    elif newer.arbitration_id == sensors.frame_id:
                        v = sensors.decode(bytes(newer.data))
                        step += 1
                command = tcu.command(SensorReading(step, v["MotorSpeed"], v["TrainSpeed"]))
                step += 1
                time.sleep(LATE_S)                              # the fault: the answer comes late
                data = cmd.encode({"TorqueRequest": min(max(command.torque_nm, 0.0), 32000.0), "SlipActive": 0,
                                   "MuEstimate": 0})
                handle.bus.send(can.Message(arbitration_id=cmd.frame_id, data=data, is_extended_id=False))
                tcu.work(command)
    finally:
        handle.close()


if __name__ == "__main__":
    sys.exit(main())
