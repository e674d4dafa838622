"""Issue 49's TCU variants: the example TCU of another make (docs/examples/python_can_tcu.py: python-can and
cantools alone, nothing of railway-hil) on ``scenarios/variants/variants.dbc``, with one fault of choice.

    python scenarios/variants/variant_tcu.py --bus udp_multicast:239.255.42.17:43117 --fault sign

Faults (``--fault``), each a unit a real TCU maker ships by mistake, and the checks of
``scenarios/variants/test_variants.toml`` it must fail (every other check passes):

- ``none``: the example as it is (creep held below the rail's peak): fails nothing;
- ``sign``: the torque it sends is the negative of the one it means (a sign error in its CAN layer): the
  wheel brakes against the driver's demand: SGN-1 (torque against the demand), ADH-2 and ADH-3 (adhesion
  used: negative), ADH-1 (it slides past twice the patch's peak creep backwards);
- ``saturate``: the torque it sends is capped at half the demand: ADH-3 (half the demand where the dry rail
  carries all of it) and STG-1 (with half the demand the wheel never slips on the patch, whose peak is about
  half the demand, so the unit never says it acts on a slip);
- ``stage0``: its SlipStage never leaves 0: STG-1;
- ``range``: from 0.3 s after it first limits the torque, MuEstimate goes out with raw value 255 (1.175,
  past the DBC's 1.0): RNG-1;
- ``freeze``: 0.3 s after it first limits the torque it sends nothing more and keeps reading (its process
  lives): the run fails as a whole (the TCU fell silent), every check with it;
- ``crash``: 0.3 s after it first limits the torque it exits with code 3: the run fails as a whole (a crash,
  the exit code in the message), every check with it.

"0.3 s after it first limits" counts readings (their cycle time, from the DBC), so a loaded machine moves
nothing in lockstep.
"""
import argparse
import importlib.util
import os
import signal
import sys
from pathlib import Path

import can
import cantools

HERE = Path(__file__).resolve().parent
#: the example TCU: beside this file (a directory of its own, as a TCU maker keeps it) or in the project's docs
EXAMPLE = next((p for p in (HERE / "python_can_tcu.py", HERE.parents[1] / "docs" / "examples" / "python_can_tcu.py")
                if p.exists()), HERE / "python_can_tcu.py")
FAULTS = ("none", "sign", "saturate", "stage0", "range", "freeze", "crash")
AFTER_S = 0.3
SLIDE_KMH = -0.5       # a creep below this: the wheel slides (SlipStage 2)


def _example():
    spec = importlib.util.spec_from_file_location("python_can_tcu", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--bus", required=True, help="INTERFACE:CHANNEL, as the example TCU")
    p.add_argument("--dbc", default=str(HERE / "variants.dbc"), help="the DBC (default: variants.dbc beside it)")
    p.add_argument("--fault", choices=FAULTS, default="none")
    args = p.parse_args()
    example = _example()
    db = cantools.database.load_file(args.dbc)
    notch, sensors, command = (db.get_message_by_name(n) for n in ("Notch", "Sensors", "TcuCmd"))
    period_s = sensors.cycle_time * 1e-3
    limiter = example.CreepLimiter(1.2, period_s)
    bus = example.open_bus(args.bus)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    demand_nm, readings, limiting_since = 0.0, 0, None
    try:
        while True:
            msg = bus.recv(timeout=1.0)
            if msg is None or msg.is_extended_id or msg.is_fd:
                continue
            if msg.arbitration_id == notch.frame_id:
                demand_nm = notch.decode(bytes(msg.data))["DemandTorque"]
                continue
            if msg.arbitration_id != sensors.frame_id:
                continue
            readings += 1
            s = sensors.decode(bytes(msg.data))
            torque_nm, limited = limiter.torque_nm(demand_nm, s["MotorSpeed"], s["TrainSpeed"])
            creep_kmh = example.KMH_PER_MS * (s["MotorSpeed"] / example.GEAR_RATIO * example.WHEEL_RADIUS_M
                                              - s["TrainSpeed"])
            if limited and limiting_since is None:
                limiting_since = readings
            late = limiting_since is not None and (readings - limiting_since) * period_s >= AFTER_S
            if args.fault == "freeze" and late:
                continue
            if args.fault == "crash" and late:
                sys.stderr.write("variant_tcu: crash (simulated) after the slip\n")
                sys.stderr.flush()
                os._exit(3)
            stage = 2 if creep_kmh < SLIDE_KMH else int(limited)
            mu = torque_nm * example.GEAR_RATIO * example.EFFICIENCY / example.WHEEL_RADIUS_M / example.AXLE_LOAD_N
            if args.fault == "sign":
                torque_nm = -torque_nm
            elif args.fault == "saturate":
                torque_nm = min(torque_nm, demand_nm / 2)
            elif args.fault == "stage0":
                stage = 0
            values = {"TorqueRequest": torque_nm, "SlipStage": stage, "MuEstimate": min(max(mu, -0.1), 1.0)}
            data = bytearray(command.encode(values))
            if args.fault == "range" and late:
                data[3] = 255                          # MuEstimate's raw byte (bits 24..31): 1.175 > 1.0
            bus.send(can.Message(arbitration_id=command.frame_id, data=bytes(data), is_extended_id=False))
    finally:
        bus.shutdown()


if __name__ == "__main__":
    sys.exit(main())
