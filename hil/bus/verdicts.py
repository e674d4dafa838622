"""The one table of what a received frame is: the codec, the plant node, the TCU node and their
counters, the log's ``/can/frames`` status and the robustness bench all name a frame's verdict
from here.

A frame is judged twice.  By itself (``hil.bus.frames.FrameCodec.classify``): does it decode, are its
values finite and in the DBC's range, does its MAC verify (``hil/bus/secoc.py``)?  Then in its stream,
by the node that receives it: is its step the next one, one already answered, or a jump?  The
stream rules for sensor readings are here (``sensor_sequence``, ``newest``), because the TCU's
answer (``TcuNode.handle``) and its backpressure after a stall (``newest_sensor_only``) must agree
on them; the plant node's rules for the TCU's frames are in ``PlantNode._accept``.

``VERDICTS``: verdict -> (what is done with the frame, what it means).  ``acted`` frames reach the
identifier or the plant; ``passed`` ones are genuine but not acted on and are not errors (counted
apart); ``rejected`` ones are counted by reason (``RejectCounter``), never acted on.  Reasons with a
signal name (``non_finite:MotorSpeed``) or an exception name (``undecodable:ValueError``) take the
prefix before the colon here.
"""
from __future__ import annotations

ACTED, PASSED, REJECTED = "acted", "passed", "rejected"

FRESH = "ok"
LATE = "late"
RESENT = "resent"
STALE = "stale_skipped"
DUPLICATE = "duplicate"
ANSWERED_TWICE = "answered_twice"
BAD_SEQUENCE = "bad_sequence"
FOREIGN = "foreign"
FORGED = "forged"
REPLAYED = "replayed"
PROBE = "probe_answer"

VERDICTS: dict[str, tuple[str, str]] = {
    FRESH: (ACTED, "decoded, authentic when authenticated, and next in its stream"),
    RESENT: (ACTED, "the TCU: a new frame for the sensor step it answered last (the plant's lockstep resend "
                    "after its command was lost): answered again with the same command"),
    LATE: (PASSED, "the plant, real time: a command for a step whose deadline passed (the held torque was "
                   "applied)"),
    PROBE: (PASSED, "the plant, a mapped bus (hil/bus/mapping.py): a command frame answering a start-up probe, "
                    "before step 0: a sign of life, not part of the run"),
    STALE: (PASSED, "the TCU, real time: a reading passed over because a newer one was queued behind it "
                    "(backpressure after a stall)"),
    DUPLICATE: (REJECTED, "the plant: a second command for the pending step (the first one stays)"),
    ANSWERED_TWICE: (REJECTED, "the plant: a command for a step already answered"),
    BAD_SEQUENCE: (REJECTED, "a step before the last one taken, or too far after it"),
    FOREIGN: (REJECTED, "the plant: a plant frame it did not send (another node's)"),
    FORGED: (REJECTED, "the MAC does not verify: another key, no key, an altered byte"),
    REPLAYED: (REJECTED, "genuine, but sent before: its freshness value was used already"),
    "unknown_id": (REJECTED, "an id the DBC does not have (or an extended id)"),
    "bad_length": (REJECTED, "not the DBC's length for its id"),
    "error_frame": (REJECTED, "a CAN error frame"),
    "remote_frame": (REJECTED, "a CAN remote frame"),
    "undecodable": (REJECTED, "cantools could not decode it"),
    "non_finite": (REJECTED, "a signal that must be finite is not"),
    "out_of_range": (REJECTED, "a signal outside the DBC's range"),
    "unmapped_id": (PASSED, "a mapped bus (hil/bus/mapping.py): an id its mapping does not name and no HIL frame's: "
                            "counted by id (the summary's unmapped_ids), not acted on"),
    "incomplete_reading": (REJECTED, "a mapped bus (hil/bus/mapping.py): the motor speed's message before any "
                                     "with the train speed"),
}


#: the verdicts a node does not count as rejected (a set for the per-frame check)
NOT_REJECTED = frozenset(v for v, (what, _) in VERDICTS.items() if what != REJECTED)


def kind(verdict: str) -> str:
    """ACTED, PASSED or REJECTED for ``verdict`` (a reason with a ``:detail`` by its prefix); a
    verdict this table does not have (a log of another version, a damaged string) is REJECTED."""
    return VERDICTS.get(verdict.split(":", 1)[0], (REJECTED,))[0]


def sensor_sequence(step: int, last_step: int, max_gap: int) -> str:
    """A PlantSensor's step at the TCU that answered ``last_step`` last (-1: none yet): FRESH when it
    follows within ``max_gap`` steps (frames may be lost), RESENT when it is ``last_step`` again,
    BAD_SEQUENCE otherwise (an old step sent again, or a jump: garbage unless the next frame
    continues it, which ``TcuNode.handle`` decides)."""
    if last_step < step <= last_step + max_gap:
        return FRESH
    return RESENT if step == last_step >= 0 else BAD_SEQUENCE


def newest(steps: dict[int, int]) -> set[int]:
    """Of the queued readings ``steps`` (batch position -> step, FRESH ones only), the positions that
    are STALE: every one but the newest step's."""
    top = max(steps.values(), default=None)
    return {i for i, step in steps.items() if step < top}
