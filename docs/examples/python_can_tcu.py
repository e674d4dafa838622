"""A traction control unit of another make, written with python-can and cantools alone (nothing of
railway-hil): it speaks its supplier's DBC (scenarios/suites/their.dbc: classical CAN, scaled integers) and
holds the wheel's creep at a set-point below the macro-slip of the rail, passing the driver's demand where
the rail carries it.

    python python_can_tcu.py --dbc their.dbc --bus udp_multicast:239.255.42.17:43117
    python python_can_tcu.py --dbc their.dbc --bus socketcan:vcan0

What it does each period: the plant sends Notch (the driver's demand torque) and then Sensors (motor and
train speed); on Sensors it answers with one TcuCmd (the torque it requests, whether it is limiting a slip,
its adhesion estimate).  The creep loop is a PI controller on the creep speed (wheel rim speed minus train
speed), its gains set from the vehicle's inertia for a bandwidth of 150 rad/s; the torque never exceeds
the demand and the integral stops where it is clamped (anti-windup).

The bus: INTERFACE:CHANNEL as railway-hil's --bus.  udp_multicast:GROUP:PORT is python-can's udp_multicast
bus, opened with hop_limit=0: a multicast datagram of TTL 0 is delivered to this machine's members and never
transmitted on a network (RFC 1112, 6.1).  On that bus a node also receives the frames it sent itself
(python-can's udp_multicast loops them back whatever receive_own_messages says): this TCU acts on the
plant's two messages and ignores every other frame, its own TcuCmd and the HIL's heartbeats included.
"""
import argparse
import signal
import sys

import can
import cantools

# The vehicle this TCU is calibrated for (railway-hil's scenarios/wet_patch.toml [vehicle]).
GEAR_RATIO = 2.788
WHEEL_RADIUS_M = 0.4375
EFFICIENCY = 0.97
MOTOR_INERTIA_KGM2 = 6.0
WHEELSET_INERTIA_KGM2 = 80.0
AXLE_LOAD_N = 13500.0 * 9.8
KMH_PER_MS = 3.6
#: the motor-side inertia: how many N.m it takes to change the creep by 1 km/h in one second
INERTIA_NM_PER_KMH_S = (MOTOR_INERTIA_KGM2 + WHEELSET_INERTIA_KGM2 / (EFFICIENCY * GEAR_RATIO ** 2)) / (
    KMH_PER_MS * WHEEL_RADIUS_M / GEAR_RATIO)
BANDWIDTH_RAD_S = 150.0
INTEGRAL_RAD_S = 20.0


class CreepLimiter:
    """torque = min(demand, I + Kp e), e = set-point - creep; I += Ki e dt while the torque is not clamped."""

    def __init__(self, set_point_kmh: float, period_s: float):
        self.set_point_kmh, self.period_s = set_point_kmh, period_s
        self.k_p = INERTIA_NM_PER_KMH_S * BANDWIDTH_RAD_S
        self.k_i = self.k_p * INTEGRAL_RAD_S
        self.integral_nm = float("inf")          # clamped to the demand at the first reading

    def torque_nm(self, demand_nm: float, motor_speed_rad_s: float, train_speed_ms: float) -> tuple[float, bool]:
        creep_kmh = KMH_PER_MS * (motor_speed_rad_s / GEAR_RATIO * WHEEL_RADIUS_M - train_speed_ms)
        error = self.set_point_kmh - creep_kmh
        self.integral_nm = min(max(self.integral_nm, 0.0), demand_nm)
        torque = self.integral_nm + self.k_p * error
        if 0.0 < torque < demand_nm:
            self.integral_nm += self.k_i * error * self.period_s
        limited = torque < demand_nm
        return min(max(torque, 0.0), demand_nm), limited


def open_bus(spec: str) -> can.BusABC:
    """INTERFACE:CHANNEL; udp_multicast:GROUP[:PORT] with hop_limit=0 (this machine only)."""
    interface, _, channel = spec.partition(":")
    if interface == "udp_multicast":
        group, _, port = channel.partition(":")
        return can.Bus(interface="udp_multicast", channel=group, port=int(port or 43113), hop_limit=0)
    return can.Bus(interface=interface, channel=channel)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--bus", required=True, help="INTERFACE:CHANNEL, e.g. udp_multicast:239.255.42.17:43117")
    p.add_argument("--dbc", required=True, help="the supplier's DBC (their.dbc)")
    p.add_argument("--set-point-kmh", type=float, default=1.2, help="the creep held on a slippery rail (km/h)")
    args = p.parse_args()
    db = cantools.database.load_file(args.dbc)
    notch, sensors, command = (db.get_message_by_name(n) for n in ("Notch", "Sensors", "TcuCmd"))
    limiter = CreepLimiter(args.set_point_kmh, sensors.cycle_time * 1e-3)
    bus = open_bus(args.bus)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))     # the bench stops it with SIGTERM
    demand_nm = 0.0
    try:
        while True:
            msg = bus.recv(timeout=1.0)
            if msg is None or msg.is_extended_id or msg.is_fd:
                continue
            if msg.arbitration_id == notch.frame_id:
                demand_nm = notch.decode(bytes(msg.data))["DemandTorque"]
            elif msg.arbitration_id == sensors.frame_id:                # a reading: answer it
                s = sensors.decode(bytes(msg.data))
                torque_nm, limited = limiter.torque_nm(demand_nm, s["MotorSpeed"], s["TrainSpeed"])
                mu = torque_nm * GEAR_RATIO * EFFICIENCY / WHEEL_RADIUS_M / AXLE_LOAD_N   # steady state
                data = command.encode({"TorqueRequest": torque_nm, "SlipActive": int(limited),
                                       "MuEstimate": min(mu, 1.275)})
                bus.send(can.Message(arbitration_id=command.frame_id, data=data, is_extended_id=False))
    finally:
        bus.shutdown()


if __name__ == "__main__":
    sys.exit(main())
