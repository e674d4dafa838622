"""The log's channels (``TOPICS``, ``PROFILE``) and their protobuf message types, built at run time
(no protoc step).

Protobuf channels decode in Rerun (``rerun run.mcap``) and Foxglove into plottable fields; a JSON
channel would arrive in Rerun as raw bytes.  Field numbers are fixed here: never renumber them.
"""
from __future__ import annotations

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

PACKAGE = "hil"
#: the header profile of the logs ``hil run`` writes: their channels are ``TOPICS``, registered in this
#: order (channel and schema ids 1, 2, ...) before the first message (``hil.log.record.McapFile``)
PROFILE = "railway-hil"

#: topic -> protobuf message name (the log's channels, in the order they are registered)
TOPICS = {
    "/plant/state": "PlantState",
    "/plant/sensor": "SensorReading",
    "/tcu/command": "TorqueCommand",
    "/tcu/observer": "ObserverSample",
    "/tcu/status": "TcuStatus",
    "/tcu/identification": "IdentificationEvent",
    "/can/frames": "CanFrame",
    "/loop/timing": "LoopTiming",
    "/run/events": "RunEvent",
    "/run/summary": "RunSummary",
    "/plant/rail": "RailTruth",
    "/control/metrics": "ControlMetrics",
    "/tcu/estimate": "PeakEstimate",
}

_T = descriptor_pb2.FieldDescriptorProto
_TYPES = {"double": _T.TYPE_DOUBLE, "int64": _T.TYPE_INT64, "uint32": _T.TYPE_UINT32, "bool": _T.TYPE_BOOL,
          "string": _T.TYPE_STRING, "bytes": _T.TYPE_BYTES, "int32": _T.TYPE_INT32}

#: message name -> [(field name, type, repeated)]
MESSAGES: dict[str, list[tuple[str, str, bool]]] = {
    "PlantState": [("step", "int64", False), ("t_s", "double", False), ("motor_speed_rad_s", "double", False),
                   ("train_speed_ms", "double", False), ("creep_speed_kmh", "double", False),
                   ("mu", "double", False), ("load_torque_nm", "double", False), ("torque_nm", "double", False),
                   ("fault_active", "bool", False), ("stage", "string", False)],
    "SensorReading": [("step", "int64", False), ("t_s", "double", False), ("motor_speed_rad_s", "double", False),
                      ("train_speed_ms", "double", False)],
    "TorqueCommand": [("step", "int64", False), ("t_s", "double", False), ("torque_nm", "double", False)],
    "ObserverSample": [("step", "int64", False), ("t_s", "double", False), ("creep_speed_kmh", "double", False),
                       ("mu_hat", "double", False), ("load_torque_nm", "double", False)],
    "TcuStatus": [("step", "int64", False), ("t_s", "double", False), ("stage", "int32", False),
                  ("stage_name", "string", False), ("correction", "int32", False)],
    "IdentificationEvent": [("step", "int64", False), ("t_s", "double", False), ("kind", "string", False),
                            ("correction", "int32", False), ("params", "double", True), ("j_ef", "double", False),
                            ("samples", "int32", False), ("strategy", "string", False),
                            ("peak_mu_ci", "double", True), ("peak_creep_ci", "double", True),
                            ("peak_open", "bool", False), ("samples_from_s", "double", False),
                            ("samples_to_s", "double", False)],
    "CanFrame": [("t_s", "double", False), ("wall_time_ns", "int64", False), ("send_time_ns", "int64", False),
                 ("arbitration_id", "uint32", False), ("is_extended_id", "bool", False), ("is_fd", "bool", False),
                 ("is_error_frame", "bool", False), ("is_remote_frame", "bool", False),
                 ("bitrate_switch", "bool", False), ("dlc", "uint32", False), ("data", "bytes", False),
                 ("direction", "string", False), ("status", "string", False)],
    "LoopTiming": [("step", "int64", False), ("t_s", "double", False), ("period_us", "double", False),
                   ("round_trip_us", "double", False), ("lateness_us", "double", False),
                   ("missed_deadline", "bool", False)],
    "RunEvent": [("t_s", "double", False), ("level", "string", False), ("text", "string", False)],
    "RunSummary": [("json", "string", False), ("identified", "bool", False), ("rt_percent", "double", False),
                   ("t_fault_s", "double", False), ("t_serious_s", "double", False),
                   ("t_identified_s", "double", False), ("r2", "double", False),
                   ("peak_mu_err_percent", "double", False), ("peak_creep_err_percent", "double", False)],
    # the truth the closed-loop metrics judge by, per step (hil/traction.py); never seen by the TCU
    "RailTruth": [("step", "int64", False), ("t_s", "double", False), ("peak_mu", "double", False),
                  ("peak_creep_kmh", "double", False), ("demand_mu", "double", False), ("segment", "int32", False)],
    "ControlMetrics": [("t_s", "double", False), ("control", "string", False),
                       ("adhesion_utilisation", "double", False), ("adhesion_utilisation_low", "double", False),
                       ("macro_slip_s", "double", False), ("macro_slip_count", "int32", False),
                       ("reaction_ms", "double", False), ("recovery_s", "double", False),
                       ("torque_ripple_percent", "double", False)],
    # the TCU's estimate of the current rail's peak, as its TcuEstimate frames bring it (identifier/peak_estimate.py)
    "PeakEstimate": [("step", "int64", False), ("t_s", "double", False), ("peak_creep_kmh", "double", False),
                     ("peak_creep_lo_kmh", "double", False), ("peak_creep_hi_kmh", "double", False),
                     ("peak_mu", "double", False), ("peak_mu_lo", "double", False), ("peak_mu_hi", "double", False),
                     ("since_step", "int64", False)],
}

#: topic -> its message's field names in order: a row written positionally (``Recorder.row``) gives its
#: values in this order
FIELDS: dict[str, tuple[str, ...]] = {topic: tuple(f[0] for f in MESSAGES[name]) for topic, name in TOPICS.items()}


def _build():
    fdp = descriptor_pb2.FileDescriptorProto(name="hil_messages.proto", package=PACKAGE, syntax="proto3")
    for name, fields in MESSAGES.items():
        msg = fdp.message_type.add(name=name)
        for number, (fname, ftype, repeated) in enumerate(fields, start=1):
            msg.field.add(name=fname, number=number, type=_TYPES[ftype],
                          label=_T.LABEL_REPEATED if repeated else _T.LABEL_OPTIONAL)
    pool = descriptor_pool.DescriptorPool()
    pool.Add(fdp)
    return {name: message_factory.GetMessageClass(pool.FindMessageTypeByName(f"{PACKAGE}.{name}"))
            for name in MESSAGES}


TYPES = _build()
