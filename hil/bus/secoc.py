"""Frame authentication in the manner of AUTOSAR SecOC: a truncated AES-CMAC over the frame id, the
payload and a freshness counter, with a key both nodes read from a file.

Every HIL frame ends its signals with a trailer (``hil/hil.dbc``: ``AuthFreshness``, 16 bits, and
``AuthMac``, 48 bits).  For a frame of id ``i`` and bytes ``d`` (the trailer zeroed), the sender's
freshness value ``FV`` (a 64-bit counter per id, 1 for the first frame of a run, one more per frame) and
the key ``K`` (AES-128):

    MAC   = CMAC_AES(K, i (2 bytes, big-endian) || d || FV (8 bytes, big-endian))      NIST SP 800-38B
    trailer = FV mod 2^16 (little-endian) || the first 6 bytes of MAC

The receiver keeps the last accepted ``FV`` per id and rebuilds the full value from the 16 bits sent,
as SecOC does: the least ``FV > last`` whose low 16 bits are the ones sent (for an id the node sends
itself, ``last`` is its own last ``FV``: a frame of that id from the bus can only be a copy).  A frame is

- ``ok`` when its MAC verifies at that ``FV`` (which then becomes ``last``: frames lost in between
  leave a gap, and the next frame is still accepted),
- ``replayed`` when it does not, but verifies at ``FV - 2^16`` or earlier values with the same low
  bits, i.e. a frame already accepted (or older) sent again: checked only on failure, for the count,
- ``forged`` otherwise (a wrong key, an altered byte, a frame made up by a node without the key).

Why a CMAC and not a checksum: only a holder of the key can make a trailer that verifies, so a third
node on the bus can neither inject a result nor alter a command; why a freshness counter: a recorded
genuine frame sent again later does not verify.  What it does not do: hide the payload (no
encryption), or protect the key file (its mode is 0600 and it lives in a directory of the user's).
"""
from __future__ import annotations

import os
import secrets
from pathlib import Path

from cryptography.hazmat.primitives.ciphers import algorithms
from cryptography.hazmat.primitives.cmac import CMAC

from ..errors import ConfigError

KEY_BYTES = 16          # AES-128
FV_BYTES = 2            # the freshness value's low bits sent in the frame
MAC_BYTES = 6           # the CMAC truncated to 48 bits
TRAILER_BYTES = FV_BYTES + MAC_BYTES
FV_MOD = 1 << (8 * FV_BYTES)
#: how many earlier 2^16 windows a failed frame is tried in before it is called forged, not replayed
REPLAY_WINDOWS = 4


def read_key(path: str | os.PathLike) -> bytes:
    """The key in ``path``: 32 hex digits (whitespace around them allowed) or 16 raw bytes."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as e:
        raise ConfigError(f"bus.auth_key_file: cannot read {p}: {e.strerror or e}") from None
    text = raw.strip()
    try:
        key = bytes.fromhex(text.decode("ascii")) if len(text) == 2 * KEY_BYTES else raw
    except (UnicodeDecodeError, ValueError):  # not hex text: the file holds the raw key bytes
        key = raw
    if len(key) != KEY_BYTES:
        raise ConfigError(f"bus.auth_key_file: {p} must hold a {8 * KEY_BYTES}-bit key (32 hex digits or "
                          f"{KEY_BYTES} bytes), found {len(raw)} bytes")
    return key


def write_key(path: str | os.PathLike) -> Path:
    """A new random key in ``path`` (32 hex digits), readable by its owner only; an existing file is
    not overwritten (``FileExistsError``)."""
    p = Path(path)
    fd = os.open(p, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(secrets.token_hex(KEY_BYTES) + "\n")
    return p


class Authenticator:
    """Protect frames a node sends and verify those it receives (module docstring).  One per node:
    the freshness counters are the node's own.  ``offsets[i]`` is where frame ``i``'s trailer starts."""

    def __init__(self, key: bytes, offsets: dict[int, int]):
        if len(key) != KEY_BYTES:
            raise ConfigError(f"bus.auth_key_file: a key is {KEY_BYTES} bytes, got {len(key)}")
        self._cmac = CMAC(algorithms.AES(key))   # keyed once; each MAC starts from a copy (1/3 of the cost)
        self.offsets = dict(offsets)
        self._sent: dict[int, int] = {}        # FV of the last frame sent, per id
        self._accepted: dict[int, int] = {}    # FV of the last frame accepted, per id

    def _mac(self, fid: int, data: bytes, fv: int) -> bytes:
        c = self._cmac.copy()
        c.update(fid.to_bytes(2, "big") + data + fv.to_bytes(8, "big"))
        return c.finalize()[:MAC_BYTES]

    def _zeroed(self, fid: int, data: bytes) -> tuple[int, bytes]:
        at = self.offsets[fid]
        return at, data[:at] + bytes(TRAILER_BYTES) + data[at + TRAILER_BYTES:]

    def protect(self, fid: int, data: bytes) -> bytes:
        """``data`` with its trailer filled: the next freshness value of ``fid`` and the MAC."""
        fv = self._sent.get(fid, 0) + 1
        self._sent[fid] = fv
        at, zeroed = self._zeroed(fid, data)
        trailer = (fv % FV_MOD).to_bytes(FV_BYTES, "little") + self._mac(fid, zeroed, fv)
        return zeroed[:at] + trailer + zeroed[at + TRAILER_BYTES:]

    def verify(self, fid: int, data: bytes) -> str:
        """``ok`` (and the frame's freshness becomes the last accepted), ``replayed`` or ``forged``."""
        at, zeroed = self._zeroed(fid, data)
        low = int.from_bytes(data[at:at + FV_BYTES], "little")
        mac = data[at + FV_BYTES:at + TRAILER_BYTES]
        # a frame of an id this node sends itself is never fresh for it: only its own, sent again
        last = max(self._accepted.get(fid, 0), self._sent.get(fid, 0))
        fv = (last - last % FV_MOD) + low
        if fv <= last:
            fv += FV_MOD
        if secrets.compare_digest(self._mac(fid, zeroed, fv), mac):
            self._accepted[fid] = fv
            return "ok"
        for back in range(1, REPLAY_WINDOWS + 1):
            old = fv - back * FV_MOD
            if old <= 0:
                break
            if secrets.compare_digest(self._mac(fid, zeroed, old), mac):
                return "replayed"
        return "forged"


#: the buses only this user's processes can reach: ``auth = "auto"`` is on there.  Not ``inprocess``:
#: no other node can put a frame on it, so a MAC would guard against nobody (``auto`` is off there;
#: ``on`` still authenticates its frames)
AUTO_AUTH_BUSES = ("local", "localbus")


def node_key(bus_settings) -> bytes | None:
    """The key a node authenticates with under the scenario's ``[bus]`` (``auth``, ``auth_key_file``):
    ``off`` none; ``on`` the key file's (which must be given); ``auto`` the key file's if one is given,
    else none (a run resolves ``auto`` itself: ``for_run``)."""
    mode, path = bus_settings.auth, bus_settings.auth_key_file
    if mode == "off" or (mode == "auto" and not path):
        return None
    if not path:
        raise ConfigError("bus.auth = \"on\" needs bus.auth_key_file (the key both nodes read)")
    return read_key(path)
